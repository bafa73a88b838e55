"""Memory given back to the system between the stages of a run: large arrays kept in a
temporary file and mapped, in memory only while they are read or written (a whole-run working
array read in a few sweeps, the welds' magnetometer regressors, is let go between the sweeps:
:func:`let_go`, ``madvise(MADV_DONTNEED)``; read again, its values come back from the file;
the file's name is removed at once, its space goes with the mapping), and the garbage in
reference cycles and the C heap's free memory (:func:`trim_heap`).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import gc
import mmap
import os
import tempfile
from typing import IO

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def file_array(shape: tuple[int, ...], min_bytes: int) -> Array:
    """A float64 array of ``shape``, zeros, in an unlinked temporary file mapped read-write when
    it takes at least ``min_bytes`` bytes (and the temporary folder has room for it), else in
    memory."""
    size = int(np.prod(shape)) * 8
    if size < max(min_bytes, 1):
        return np.zeros(shape)
    try:
        with tempfile.TemporaryFile(prefix="pipe_nav_mapped_") as f:
            f.truncate(size)
            m = mmap.mmap(f.fileno(), size)  # shared: what is let go stays in the file
    except OSError:  # no room for the file (a full or read-only temporary folder)
        return np.zeros(shape)
    return np.frombuffer(m, dtype=np.float64).reshape(shape)


class Spool:
    """float64 rows gathered piece by piece in an unlinked temporary file and then mapped
    read-only (:meth:`gathered`): an array that is never whole in memory while it is built,
    nor twice when it is joined. ``row``: the shape of one row (``()`` for a vector). Where the
    temporary folder has no room (or no file can be made or mapped), the rows are kept in memory
    instead, from the first that could not be written on; the array gathered is the same."""

    def __init__(self, row: tuple[int, ...] = ()) -> None:
        self.row = row
        self.rows = 0  # written to the file
        self._file: IO[bytes] | None = None
        self._kept: list[Array] | None = None  # the rows in memory, once the file failed
        try:
            self._file = tempfile.TemporaryFile(prefix="pipe_nav_mapped_")  # noqa: SIM115 - held open while rows come
        except OSError:
            self._kept = []

    @property
    def in_file(self) -> bool:
        """Whether the rows are in the file (False once it had no room, or none was made)."""
        return self._file is not None

    def append(self, a: Array) -> None:
        """Add the rows of ``a`` (shape (n, *row)) after those appended before."""
        a = np.ascontiguousarray(a, dtype=np.float64)
        if self._file is not None:
            try:  # unbuffered: once written, the rows are the file's (a full disk raises here)
                data, fd, done = memoryview(a.reshape(-1).view(np.uint8)), self._file.fileno(), 0
                while done < len(data):
                    done += os.write(fd, data[done:])
                self.rows += len(a)
                return
            except OSError:  # no room: what was written comes back into memory
                self._to_memory()
        assert self._kept is not None
        self._kept.append(a)

    def gathered(self) -> Array:
        """Every row appended, in order, mapped read-only from the file (in memory where it
        could not be). The spool is spent."""
        if self._file is not None and self.rows:
            try:
                m = mmap.mmap(self._file.fileno(), 0, access=mmap.ACCESS_READ)
            except (OSError, ValueError):
                self._to_memory()
            else:
                self._file.close()
                count = self.rows * self._width
                return np.frombuffer(m, np.float64, count).reshape((self.rows, *self.row))
        if self._file is not None:
            self._file.close()
        kept = self._kept or []
        return np.concatenate(kept) if kept else np.empty((0, *self.row))

    @property
    def _width(self) -> int:
        return int(np.prod(self.row, dtype=np.int64))

    def _to_memory(self) -> None:
        assert self._file is not None
        self._file.seek(0)
        back = np.fromfile(self._file, dtype=np.float64, count=self.rows * self._width)
        self._file.close()
        self._file = None
        self._kept = [back.reshape((self.rows, *self.row))]


def let_go(a: Array) -> None:
    """Give back the memory of an array from :func:`file_array` (its pages leave the process;
    read again, they come back from the file). Nothing for an array in memory."""
    m = mapping(a)
    if m is not None:
        m.madvise(mmap.MADV_DONTNEED)


def mapping(a: Array) -> mmap.mmap | None:
    """The file mapping whose memory ``a`` is, from its start (None for other arrays)."""
    base = root(a)
    view = base.base
    m = view.obj if isinstance(view, memoryview) else view
    return m if isinstance(m, mmap.mmap) and base.ctypes.data == a.ctypes.data else None


def root(a: Array) -> Array:
    """The array at the end of ``a``'s chain of views (``a`` itself when it has its own memory
    or views a buffer that is not an array)."""
    while isinstance(a.base, np.ndarray):
        a = a.base
    return a


ARENAS = 2  # C heaps (glibc arenas) a command line process allocates from


def limit_arenas(arenas: int = ARENAS) -> None:
    """Let the C allocator use at most ``arenas`` heaps (glibc's ``M_ARENA_MAX``; nothing
    elsewhere), before the process starts its threads: by default each thread that allocates
    while another does gets a heap of its own (up to 8 per core), and what one frees the
    others do not reuse (BENCHMARKS.md: the 100 km run's peak)."""
    libc = _c_library()
    if libc is not None and hasattr(libc, "mallopt"):
        libc.mallopt(-8, int(arenas))  # M_ARENA_MAX


# blocks the C allocator serves from its heaps, and the free memory it keeps at a heap's top for
# the next ones (glibc's M_MMAP_THRESHOLD and M_TRIM_THRESHOLD: keep_freed)
KEEP_BELOW = 32 << 20
KEEP_UP_TO = 256 << 20


def keep_freed(below: int = KEEP_BELOW, up_to: int = KEEP_UP_TO) -> None:
    """Have the C allocator serve blocks under ``below`` bytes from its heaps and keep up to
    ``up_to`` bytes freed at a heap's top for the next (glibc's ``M_MMAP_THRESHOLD`` and
    ``M_TRIM_THRESHOLD``; nothing elsewhere, nor where the environment sets them: the
    ``MALLOC_*_`` variables or ``GLIBC_TUNABLES``). A run allocates and frees arrays of a few
    MB by the thousand (a chunk's decompressed records, the checks' and the passes' batches):
    by default glibc maps many of them afresh and gives them back at once, and every first
    write of a page of one is a page fault (a fifth of the 10 km run's 250 k were such; the
    run's peak is some 40 MB higher for it). A long run gives the freed memory back between
    its stages all the same (:func:`trim_heap`)."""
    if "glibc.malloc" in os.environ.get("GLIBC_TUNABLES", "") or any(
        k in os.environ for k in ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")
    ):
        return
    libc = _c_library()
    if libc is not None and hasattr(libc, "mallopt"):
        libc.mallopt(-3, int(below))  # M_MMAP_THRESHOLD
        libc.mallopt(-1, int(up_to))  # M_TRIM_THRESHOLD


def small_pages() -> None:
    """Have numpy's large arrays take the system's ordinary pages, unless the environment says
    otherwise (``NUMPY_MADVISE_HUGEPAGE``). numpy asks for transparent huge pages on every
    array of 4 MB and more (``madvise(MADV_HUGEPAGE)``), and where the kernel then compacts
    memory to find them as the array is first written (``transparent_hugepage/defrag`` set
    to ``madvise``, the default of many distributions and of these machines) a run stalls:
    the first write of 240 MB took 0.02-2.0 s so, against 0.10-0.12 s in ordinary pages, and
    the 10 km run lost 1-1.5 s of its 6-7 (BENCHMARKS.md). Process-wide: the command line
    and the nodes call it first."""
    if "NUMPY_MADVISE_HUGEPAGE" in os.environ:
        return
    try:
        from numpy._core.multiarray import _set_madvise_hugepage
    except ImportError:  # numpy 1.x
        from numpy.core.multiarray import _set_madvise_hugepage
    _set_madvise_hugepage(False)


# IMU samples of a run (under 3 h at 200 Hz) below which trim_heap leaves the heap alone: the
# 10 km run's garbage raises its peak by 20 MB, and the five trims cost it 0.09 s
TRIM_MIN_SAMPLES = 2_000_000


def trim_heap(samples: int | None = None) -> None:
    """Collect the garbage held in reference cycles (a finished pass's navigator and its
    recording wait in one until Python's collector happens to run: at 100 km some 0.9 GB
    after the smoothing), then give the C heap's free memory back to the system (glibc's
    ``malloc_trim``; nothing elsewhere): the allocator keeps what numpy frees below its mmap
    threshold (batches of a few MB), some 0.3 GB after the smoothing at 100 km, which the
    products stages would otherwise have on top of their own. ``samples``: the run's IMU
    samples; a run of fewer than :data:`TRIM_MIN_SAMPLES` is left as it is (a full
    collection costs some 0.02 s)."""
    if samples is not None and samples < TRIM_MIN_SAMPLES:
        return
    gc.collect()
    libc = _c_library()
    if libc is not None and hasattr(libc, "malloc_trim"):
        libc.malloc_trim(0)


@functools.cache
def _c_library() -> ctypes.CDLL | None:
    """The C library, loaded once (None where there is none to load)."""
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None
