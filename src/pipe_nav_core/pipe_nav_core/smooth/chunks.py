"""Chunked row storage for the forward pass's recording (:mod:`.recording`) and the batch
solver: arrays that grow along their first axis, and fixed-width rows kept in chunks of
CHUNK_EPOCHS rows, the oldest written to a temporary directory beyond a memory budget and read
back on demand, with a pool of spare chunk arrays shared by every recording.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import threading
import weakref
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

RAM_BUDGET_BYTES = 128 * 2**20  # packed covariance rows kept in memory; older chunks spill
# epochs per chunk of packed rows: 60 MB with 38 error states, above the size up to which
# the C allocator keeps freed memory instead of returning it to the system (32 MB)
CHUNK_EPOCHS = 4096
TRIM_SLACK = 0.125  # Growable.trim copies an array reserved over this fraction beyond its rows


class Growable:
    """An array that grows along its first axis: amortized O(1) extends, one contiguous
    buffer (``data`` is a view of the rows filled so far)."""

    def __init__(
        self, row_shape: tuple[int, ...] = (), dtype: type = np.float64, capacity: int = 256
    ) -> None:
        self._a = np.empty((max(capacity, 1), *row_shape), dtype=dtype)
        self._n = 0

    def _reserve(self, extra: int) -> None:
        need = self._n + extra
        if need > len(self._a):
            self.reserve(max(need, 2 * len(self._a)))

    def reserve(self, rows: int) -> None:
        """Room for ``rows`` rows in all (a guess: more rows still fit, by growing)."""
        if rows > len(self._a):
            a = np.empty((rows, *self._a.shape[1:]), self._a.dtype)
            a[: self._n] = self._a[: self._n]
            self._a = a

    def extend(self, rows: Array) -> None:
        self._reserve(len(rows))
        self._a[self._n : self._n + len(rows)] = rows
        self._n += len(rows)

    @property
    def data(self) -> Array:
        return self._a[: self._n]

    def trim(self) -> None:
        """Let go of the room reserved beyond the rows filled when it is over TRIM_SLACK of
        them (a copy: views of ``data`` taken before keep the old buffer)."""
        if len(self._a) > (1.0 + TRIM_SLACK) * self._n:
            self._a = self._a[: self._n].copy()


# Chunk arrays no recording uses any more (spilled, or of a closed recording), by shape, for
# the next chunks: memory the process has written before costs nothing to write again, while
# fresh memory costs a page fault per 4 kB (0.10-0.12 s for a 10 km pass's 240 MB here, in
# small pages: memory.small_pages). At most RAM_BUDGET_BYTES are kept, or READ_BUFFERS chunks
# if more: the RTS after a forward pass reads the spilled chunks back into READ_BUFFERS
# arrays, which a recording's chunks (read_back) write beforehand in their writer thread as
# they first spill. drop_spare() frees them.
_SPARE: dict[tuple[int, ...], list[Array]] = {}
_SPARE_LOCK = threading.Lock()
_READ_BACK: set[tuple[int, ...]] = set()  # the chunk shapes of Chunks(read_back=True)


READ_BUFFERS = 3  # chunks read back from disk that a caller may still be reading
# chunks a recording may have waiting for the disk: beyond, the next spill waits for the
# oldest write. Unbounded, the chunks of a pass that records faster than the disk writes (the
# 100 km line at 10 Hz epochs: 7.8 GB a pass, 0.2-0.3 GB/s, at a 0.2 GB/s disk) queued in
# memory: its peak went from 1.8 to 2.7 GB as the disk slowed
PENDING_WRITES = 2


def _take(rows: int, width: int) -> Array:
    """A (rows, width) array: a spare one if there is one, else a new one."""
    shape = (rows, width)
    with _SPARE_LOCK:
        spare = _SPARE.get(shape)
        if spare:
            return spare.pop()
    return np.empty(shape)


def _give(chunk: Array) -> None:
    """Keep a chunk array no recording uses any more for the next (within the budget)."""
    with _SPARE_LOCK:
        spare = _SPARE.setdefault(chunk.shape, [])
        read = READ_BUFFERS * chunk.nbytes if chunk.shape in _READ_BACK else 0
        if (len(spare) + 1) * chunk.nbytes <= max(RAM_BUDGET_BYTES, read):
            spare.append(chunk)


def _prepare_spare(shape: tuple[int, int], count: int) -> None:
    """Arrays of shape, written (their pages faulted in), into the spare pool until it holds
    count of them."""
    with _SPARE_LOCK:
        missing = count - len(_SPARE.get(shape, []))
    for _ in range(missing):
        a = np.empty(shape)
        a.fill(0.0)
        _give(a)


def drop_spare() -> None:
    """Free the spare chunk arrays (after a smoothing, say)."""
    with _SPARE_LOCK:
        _SPARE.clear()


class Chunks:
    """Fixed-width float64 rows in chunks of ``rows`` rows (CHUNK_EPOCHS unless given: a wide
    row, the graph eliminator's 23 kB, wants fewer); beyond budget bytes in
    memory the oldest full chunks are written to a temporary directory (in a background
    thread: the array stays in use until its file is complete, then serves a later chunk).
    Chunks read back from disk go into READ_BUFFERS buffers in turn: a caller holds at most the
    rows of the last ones it asked for (:func:`~pipe_nav_core.smooth.rts.rts_packed` reads one
    chunk ahead while the gains of the one before take the first row of the one after).
    read_back: every chunk will be read back (a Recording's, by the RTS): the READ_BUFFERS
    arrays for that are written as the chunks first spill, and kept as spares."""

    def __init__(
        self, width: int, budget: int, rows: int | None = None, *, read_back: bool = False
    ) -> None:
        self.width = width
        self._read_back = read_back
        self.chunk_rows = CHUNK_EPOCHS if rows is None else rows
        if read_back:
            with _SPARE_LOCK:
                _READ_BACK.add((self.chunk_rows, width))
        self._chunks: list[Array | str] = []  # in memory, or the path of a spilled chunk
        self._n = 0
        self._in_ram = self._fitting(budget)  # chunks kept
        self._oldest_in_ram = 0
        self._dir: str | None = None
        self._writer: ThreadPoolExecutor | None = None
        self._writes: list[Future[None]] = []
        self._finalizer: weakref.finalize | None = None
        self._read: list[tuple[int, Array]] = []  # the last chunks read back from disk

    def expect(self, rows: int) -> None:
        """Before any row is claimed: ``rows`` rows are expected. Where they do not fit in the
        budget (they will spill anyway) only RAM_BUDGET_BYTES are kept in memory: a larger
        budget would only raise the peak (the 100 km line's at 10 Hz epochs)."""
        if self._n or rows <= self._in_ram * self.chunk_rows:
            return
        self._in_ram = min(self._in_ram, self._fitting(RAM_BUDGET_BYTES))

    def _fitting(self, budget: int) -> int:
        """The chunks kept in memory within budget bytes (at least two)."""
        return max(2, budget // (self.chunk_rows * self.width * 8))

    def __len__(self) -> int:
        return self._n

    def claim(self, count: int) -> list[tuple[int, int, Array]]:
        """The next count rows, to be filled by the caller: (a, b, view of rows a..b-1)."""
        out = []
        done = 0
        while done < count:
            i, j = divmod(self._n, self.chunk_rows)
            if j == 0:
                self._chunks.append(_take(self.chunk_rows, self.width))
                if len(self._chunks) - self._oldest_in_ram > self._in_ram:
                    self._spill(self._oldest_in_ram)
                    self._oldest_in_ram += 1
            chunk = self._chunks[i]
            assert not isinstance(chunk, str)
            take = min(count - done, self.chunk_rows - j)
            out.append((done, done + take, chunk[j : j + take]))
            done += take
            self._n += take
        return out

    def _spill(self, i: int) -> None:
        if self._dir is None:
            self._dir = tempfile.mkdtemp(prefix="pipe_nav_recording_")
            self._writer = ThreadPoolExecutor(max_workers=1)
            self._finalizer = weakref.finalize(self, _remove, self._dir, self._writer)
            if self._read_back:
                # the arrays the chunks will be read back into, written while the writer
                # waits for chunks to spill (not by the reader, beside the smoother's threads)
                shape = (self.chunk_rows, self.width)
                self._writer.submit(_prepare_spare, shape, READ_BUFFERS)
        for job in [w for w in self._writes if w.done()]:
            self._writes.remove(job)
            job.result()  # a failed write (disk full) raises here
        while len(self._writes) >= PENDING_WRITES:
            self._writes[0].result()
            del self._writes[0]
        path = os.path.join(self._dir, f"{i}.bin")  # raw float64 rows
        chunks, chunk = self._chunks, self._chunks[i]

        def write() -> None:
            chunk.tofile(path)
            chunks[i] = path  # read back from the file from now on
            _give(chunk)

        assert self._writer is not None
        self._writes.append(self._writer.submit(write))

    def flush(self) -> None:
        """Wait for the pending writes (raising a failed one)."""
        for job in self._writes:
            job.result()
        self._writes = []

    def chunk(self, i: int) -> Array:
        """Rows of chunk i (the filled ones), from memory or read back from disk. The pending
        writes end first: a chunk's array goes back to the pool when its file is complete,
        and a caller still holding it would see it refilled with another chunk's rows."""
        if self._writes:
            self.flush()
        c = self._chunks[i]
        if isinstance(c, str):
            hit = [(k, a) for k, a in self._read if k == i]
            if hit:  # now the last asked for: the buffers are reused least recently asked first
                self._read.remove(hit[0])
                self._read.append(hit[0])
                c = hit[0][1]
            else:
                full = len(self._read) == READ_BUFFERS
                buf = self._read.pop(0)[1] if full else _take(self.chunk_rows, self.width)
                with open(c, "rb") as f:
                    if f.readinto(memoryview(buf).cast("B")) != buf.nbytes:
                        raise OSError(f"{c}: a spilled chunk of the recording is cut short")
                self._read.append((i, buf))
                c = buf
        return c[: min(self.chunk_rows, self._n - i * self.chunk_rows)]

    def rows(self, ks: Array) -> Array:
        """The rows of the given indices (B, width), in that order."""
        ks = np.asarray(ks, dtype=np.int64)
        out = np.empty((len(ks), self.width))
        ci = ks // self.chunk_rows
        for i in np.unique(ci):
            sel = ci == i
            out[sel] = self.chunk(int(i))[ks[sel] - i * self.chunk_rows]
        return out

    @property
    def n_chunks(self) -> int:
        return len(self._chunks)

    def close(self) -> None:
        if self._finalizer is not None:
            self._finalizer()  # the pending writes end first (and give their arrays back)
        for c in [*self._chunks, *(a for _, a in self._read)]:
            if not isinstance(c, str):
                _give(c)
        self._chunks, self._read, self._n = [], [], 0


def _remove(directory: str, writer: ThreadPoolExecutor) -> None:
    """Wait for the pending writes, then remove the spill directory."""
    writer.shutdown(wait=True)
    shutil.rmtree(directory, ignore_errors=True)
