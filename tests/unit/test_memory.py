"""Memory given back between stages (pipe_nav_core.memory): arrays in files keep their values
when let go, and trimming the heap leaves every live array as it was."""

from __future__ import annotations

import numpy as np

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


def test_limiting_the_arenas_before_threads_start_keeps_allocating():
    """limit_arenas (glibc M_ARENA_MAX, what the command line sets first) leaves numpy
    allocating and freeing as before, from threads too."""
    from concurrent.futures import ThreadPoolExecutor

    memory.limit_arenas(2)
    with ThreadPoolExecutor(max_workers=4) as pool:
        sums = list(pool.map(lambda k: float(np.full(1 << 16, float(k)).sum()), range(8)))
    assert sums == [float(k << 16) for k in range(8)]
