"""Memory given back between stages (pipe_nav_core.memory): arrays in files keep their values
when let go, and trimming the heap leaves every live array as it was."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from pipe_nav_core import memory


def test_an_array_in_a_file_keeps_its_values_when_let_go():
    a = memory.file_array((1000, 10), min_bytes=0)
    assert not a.any() and a.flags.writeable and a.flags.c_contiguous
    a[:] = np.arange(a.size).reshape(a.shape) * 0.5
    before = a.copy()
    memory.let_go(a)  # its pages leave the process: read again from the file
    assert a.tobytes() == before.tobytes()
    small = memory.file_array((3, 2), min_bytes=1 << 20)  # under the size: in memory
    assert small.base is None and not small.any()
    memory.let_go(small)  # nothing for an array in memory
    assert not small.any()


def test_trimming_the_heap_keeps_live_arrays():
    keep = [np.full(1000 + k, float(k)) for k in range(200)]
    freed = [np.ones(1 << 16) for _ in range(50)]
    del freed
    memory.trim_heap()
    memory.trim_heap()  # twice: the C library is loaded once
    assert all(np.all(a == k) for k, a in enumerate(keep))


def test_a_short_runs_heap_is_not_trimmed(monkeypatch):
    """trim_heap(samples): a full collection and malloc_trim for a long run only."""
    collected: list[int] = []
    monkeypatch.setattr(memory.gc, "collect", lambda: collected.append(1) or 0)
    memory.trim_heap(memory.TRIM_MIN_SAMPLES - 1)
    assert not collected
    memory.trim_heap(memory.TRIM_MIN_SAMPLES)
    memory.trim_heap()
    assert len(collected) == 2


def test_limiting_the_arenas_before_threads_start_keeps_allocating():
    """limit_arenas (glibc M_ARENA_MAX, what the command line sets first) leaves numpy
    allocating and freeing as before, from threads too."""
    from concurrent.futures import ThreadPoolExecutor

    memory.limit_arenas(2)
    with ThreadPoolExecutor(max_workers=4) as pool:
        sums = list(pool.map(lambda k: float(np.full(1 << 16, float(k)).sum()), range(8)))
    assert sums == [float(k << 16) for k in range(8)]


_KEEP_FREED = """
import resource
import numpy as np
from pipe_nav_core import memory

def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt

def churn():  # four 8 MB arrays written and freed, ten times over
    f0 = faults()
    for _ in range(10):
        held = [np.ones(1 << 20) for _ in range(4)]
        assert all(float(a.sum()) == 1 << 20 for a in held)
        del held
    return faults() - f0

memory.small_pages()  # as the command line: ordinary pages, one fault each
churn()
before = churn()  # glibc's defaults: the 32 MB freed at once is given back, then faulted in
memory.keep_freed()
churn()
after = churn()
print(before, after)
assert before > 10 * 4 * 2048 * 0.9 and after < 500, (before, after)
"""


def test_keeping_freed_memory_spares_the_page_faults_of_the_next_arrays():
    """memory.keep_freed (what the command line sets first): arrays of a few MB allocated and
    freed over and over reuse the same memory instead of being mapped and faulted in afresh
    (counted in a fresh process, the allocator's settings left as glibc's defaults)."""
    env = {k: v for k, v in os.environ.items()
           if k != "GLIBC_TUNABLES" and not k.startswith("MALLOC_")}  # fmt: skip
    subprocess.run([sys.executable, "-c", _KEEP_FREED], check=True, env=env, timeout=120)


_SMALL_PAGES = """
import os
import numpy as np
from pipe_nav_core import memory

def advised(a):
    # whether the kernel mapping holding the middle of a was advised MADV_HUGEPAGE ("hg" in
    # its VmFlags; numpy advises only the whole huge pages inside)
    address, found, inside = a.ctypes.data + a.nbytes // 2, False, False
    with open("/proc/self/smaps") as f:
        for line in f:
            head = line.split(maxsplit=1)[0]
            if "-" in head and not head.endswith(":"):
                lo, hi = (int(x, 16) for x in head.split("-"))
                inside = lo <= address < hi
            elif inside and head == "VmFlags:":
                found = "hg" in line.split()[1:]
    return found

assert advised(np.ones(1 << 23))  # numpy's default: 64 MB asks
os.environ["NUMPY_MADVISE_HUGEPAGE"] = "1"
memory.small_pages()  # the user said so: left as it is
assert advised(np.ones(1 << 23))
del os.environ["NUMPY_MADVISE_HUGEPAGE"]
memory.small_pages()
a = np.ones(1 << 23)
assert not advised(a) and a.sum() == a.size
print("ok")
"""


@pytest.mark.skipif(not os.path.exists("/proc/self/smaps"), reason="Linux mappings only")
def test_small_pages_stop_numpy_asking_for_huge_pages():
    """small_pages (what the command line and the nodes call first): a large array is no
    longer advised MADV_HUGEPAGE (numpy's default does, and where the kernel compacts memory
    for it the first write stalls); NUMPY_MADVISE_HUGEPAGE in the environment is obeyed.
    In a fresh interpreter, as the command line starts: in this one, after hundreds of tests
    with numpy's default, a new 64 MB array can be put in memory advised before (it failed
    so in the full suite, twice, though never alone)."""
    env = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    run = subprocess.run([sys.executable, "-c", _SMALL_PAGES], env=env, capture_output=True,
                         text=True, timeout=120)  # fmt: skip
    assert run.returncode == 0 and run.stdout.strip() == "ok", run.stderr


def test_a_spool_gathers_its_rows_in_a_file_or_in_memory(monkeypatch):
    """memory.Spool: rows appended piece by piece come back in order, mapped read-only from a
    file; where the file has no room from the start, or runs out of it half-way, the same
    rows come back from memory."""
    import resource
    import signal
    import tempfile

    rng = np.random.default_rng(3)
    pieces = [rng.normal(size=(n, 3)) for n in (5, 0, 17, 1, 40)]
    whole = np.concatenate(pieces)

    def gather() -> tuple[np.ndarray, bool]:
        s = memory.Spool((3,))
        for p in pieces:
            s.append(p)
        return s.gathered(), s.in_file

    got, in_file = gather()
    assert got.tobytes() == whole.tobytes() and got.shape == whole.shape and in_file
    assert memory.mapping(got) is not None and not got.flags.writeable
    vec = memory.Spool()
    vec.append(whole[:, 0])
    assert vec.gathered().tobytes() == np.ascontiguousarray(whole[:, 0]).tobytes()
    assert memory.Spool((3,)).gathered().shape == (0, 3)  # nothing appended

    # the file runs out of room at the last piece (a file size limit: EFBIG, as a full disk)
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    old = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    try:
        resource.setrlimit(resource.RLIMIT_FSIZE, (600, hard))
        got, in_file = gather()
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, old)
    assert not in_file and got.tobytes() == whole.tobytes() and memory.mapping(got) is None

    def no_room(*_args, **_kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(tempfile, "TemporaryFile", no_room)
    got, in_file = gather()
    assert not in_file and got.tobytes() == whole.tobytes() and memory.mapping(got) is None
