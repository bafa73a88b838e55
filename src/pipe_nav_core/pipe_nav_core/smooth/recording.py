"""What the smoothers need from a forward filter pass, in compact contiguous storage.

Per epoch (k = 0 is the alignment): the filter's estimate and its linearization point as flat
state vectors (:data:`pipe_nav_core.model.state.SV_SIZE`), the mean error state, and one packed row
of covariances and transition for the RTS smoother (:class:`pipe_nav_core.smooth.rts.EpochRows`).
Per IMU sample: the nominal trajectory the corrections are applied to.

The packed rows are the bulk (some 15 kB per epoch with 38 error states): they are kept in
chunks of CHUNK_EPOCHS epochs, and beyond RAM_BUDGET_BYTES the oldest chunks go to a temporary
directory, removed when the recording is closed or garbage collected. The smoother reads them
back from the last to the first (:meth:`Recording.rts_chunks`).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import threading
import weakref
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.model.state import SV_SIZE, Layout
from pipe_nav_core.smooth.rts import EpochRows

Array = NDArray[np.float64]

RAM_BUDGET_BYTES = 256 * 2**20  # packed covariance rows kept in memory; older chunks spill
# epochs per chunk of packed rows: 60 MB with 38 error states, above the size up to which
# the C allocator keeps freed memory instead of returning it to the system (32 MB)
CHUNK_EPOCHS = 4096
# the per-sample nominal is thinned to about one sample per this many seconds, never sparser
# (0: every IMU sample): the centreline is resampled every 0.5 m of chainage for the products
SAMPLE_SPACING_S = 0.02


def phi_rows(layout: Layout) -> Array:
    """The rows of the error-state transition that can differ from the identity: attitude,
    velocity and position (the only nonzero rows of the system matrix; process.discretize_k)
    and the odometer reading errors (shifted each epoch)."""
    rows = np.arange(layout.pos.stop)
    if layout.odoq is not None:
        rows = np.r_[rows, np.arange(layout.odoq.start, layout.odoq.stop)]
    return rows


class _Growable:
    """An array that grows along its first axis: amortized O(1) extends, one contiguous
    buffer (``data`` is a view of the rows filled so far)."""

    def __init__(self, row_shape: tuple[int, ...] = (), dtype: type = np.float64) -> None:
        self._a = np.empty((256, *row_shape), dtype=dtype)
        self._n = 0

    def _reserve(self, extra: int) -> None:
        need = self._n + extra
        if need > len(self._a):
            a = np.empty((max(need, 2 * len(self._a)), *self._a.shape[1:]), self._a.dtype)
            a[: self._n] = self._a[: self._n]
            self._a = a

    def extend(self, rows: Array) -> None:
        self._reserve(len(rows))
        self._a[self._n : self._n + len(rows)] = rows
        self._n += len(rows)

    @property
    def data(self) -> Array:
        return self._a[: self._n]


# Chunk arrays no recording uses any more (spilled, or of a closed recording), by shape, for
# the next chunks: memory the process has written before costs nothing to write again, while
# fresh memory costs a page fault per 4 kB (on a virtual machine up to 10 us each, ten times
# the packing itself). At most RAM_BUDGET_BYTES are kept; drop_spare() frees them.
_SPARE: dict[tuple[int, ...], list[Array]] = {}
_SPARE_LOCK = threading.Lock()


READ_BUFFERS = 3  # chunks read back from disk that a caller may still be reading


def _take(width: int) -> Array:
    """A (CHUNK_EPOCHS, width) array: a spare one if there is one, else a new one."""
    shape = (CHUNK_EPOCHS, width)
    with _SPARE_LOCK:
        spare = _SPARE.get(shape)
        if spare:
            return spare.pop()
    return np.empty(shape)


def _give(chunk: Array) -> None:
    """Keep a chunk array no recording uses any more for the next (within the budget)."""
    with _SPARE_LOCK:
        spare = _SPARE.setdefault(chunk.shape, [])
        if (len(spare) + 1) * chunk.nbytes <= RAM_BUDGET_BYTES:
            spare.append(chunk)


def drop_spare() -> None:
    """Free the spare chunk arrays (after a smoothing, say)."""
    with _SPARE_LOCK:
        _SPARE.clear()


class _Chunks:
    """Fixed-width float64 rows in chunks of CHUNK_EPOCHS rows; beyond budget bytes in
    memory the oldest full chunks are written to a temporary directory (in a background
    thread: the array stays in use until its file is complete, then serves a later chunk).
    Chunks read back from disk go into READ_BUFFERS buffers in turn: a caller holds at most the
    rows of the last ones it asked for (:func:`~pipe_nav_core.smooth.rts.rts_packed` reads one
    chunk ahead while the gains of the one before take the first row of the one after)."""

    def __init__(self, width: int, budget: int) -> None:
        self.width = width
        self._chunks: list[Array | str] = []  # in memory, or the path of a spilled chunk
        self._n = 0
        self._in_ram = max(2, budget // (CHUNK_EPOCHS * width * 8))  # chunks kept
        self._oldest_in_ram = 0
        self._dir: str | None = None
        self._writer: ThreadPoolExecutor | None = None
        self._writes: list[Future[None]] = []
        self._finalizer: weakref.finalize | None = None
        self._read: list[tuple[int, Array]] = []  # the last chunks read back from disk

    def __len__(self) -> int:
        return self._n

    def claim(self, count: int) -> list[tuple[int, int, Array]]:
        """The next count rows, to be filled by the caller: (a, b, view of rows a..b-1)."""
        out = []
        done = 0
        while done < count:
            i, j = divmod(self._n, CHUNK_EPOCHS)
            if j == 0:
                self._chunks.append(_take(self.width))
                if len(self._chunks) - self._oldest_in_ram > self._in_ram:
                    self._spill(self._oldest_in_ram)
                    self._oldest_in_ram += 1
            chunk = self._chunks[i]
            assert not isinstance(chunk, str)
            take = min(count - done, CHUNK_EPOCHS - j)
            out.append((done, done + take, chunk[j : j + take]))
            done += take
            self._n += take
        return out

    def _spill(self, i: int) -> None:
        if self._dir is None:
            self._dir = tempfile.mkdtemp(prefix="pipe_nav_recording_")
            self._writer = ThreadPoolExecutor(max_workers=1)
            self._finalizer = weakref.finalize(self, _remove, self._dir, self._writer)
        for job in [w for w in self._writes if w.done()]:
            self._writes.remove(job)
            job.result()  # a failed write (disk full) raises here
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
                buf = self._read.pop(0)[1] if full else _take(self.width)
                with open(c, "rb") as f:
                    if f.readinto(memoryview(buf).cast("B")) != buf.nbytes:
                        raise OSError(f"{c}: a spilled chunk of the recording is cut short")
                self._read.append((i, buf))
                c = buf
        return c[: min(CHUNK_EPOCHS, self._n - i * CHUNK_EPOCHS)]

    def rows(self, ks: Array) -> Array:
        """The rows of the given indices (B, width), in that order."""
        ks = np.asarray(ks, dtype=np.int64)
        out = np.empty((len(ks), self.width))
        ci = ks // CHUNK_EPOCHS
        for i in np.unique(ci):
            sel = ci == i
            out[sel] = self.chunk(int(i))[ks[sel] - i * CHUNK_EPOCHS]
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


class Recording:
    """What the smoothers need from a forward pass (see the module docstring).

    Per epoch k (arrays with K rows): ``states`` (K, SV_SIZE) the filter's estimate after the
    update (flat, :meth:`NavState.vector`; ``t`` its times, s); ``lin`` the linearization
    point (the estimate itself for the ordinary EKF, the reference state when the filter runs
    about a reference trajectory); ``x_upd`` (K, n) the filter's mean error state relative to
    it (zero for the EKF); ``dx`` (K, n) updated minus predicted mean error state (what an RTS
    smoother carries back); ``end_offset`` (K, n) lin (-) the nominal at the end of the block
    (the correction that moves the per-sample nominal onto the linearization point; dx for the
    EKF); the predicted and updated covariances and Phi from k-1 to k (:meth:`P_upd`,
    :meth:`P_pred`, :meth:`phi`, packed: :meth:`rts_chunks`).
    Per kept IMU sample: ``s_t`` s, ``s_odo`` raw odometer distance m, nominal ``s_lat``,
    ``s_lon`` rad, ``s_h`` m, ``s_q`` [x, y, z, w] base_link -> ENU, and ``s_epoch``: the
    epoch whose block the sample belongs to (the block of epoch k starts at lin[k - 1]).

    reference: the trajectory (K, SV_SIZE) the filter runs about, if any: it is lin (not
    copied), and x_upd and end_offset are stored; without one they follow from states and dx.
    """

    def __init__(
        self,
        layout: Layout,
        *,
        reference: Array | None = None,
        ram_budget: int = RAM_BUDGET_BYTES,
    ) -> None:
        self.layout = layout
        self._reference = reference
        linearized = self.linearized = reference is not None
        self.format = EpochRows(layout.n, phi_rows(layout))
        self._packed = _Chunks(self.format.width, ram_budget)
        self._packer: ThreadPoolExecutor | None = None
        self._packing: Future[None] | None = None
        n = layout.n
        self._states = _Growable((SV_SIZE,))
        self._dx = _Growable((n,))
        self._x_upd = _Growable((n,)) if linearized else None
        self._end_offset = _Growable((n,)) if linearized else None
        self._s = {name: _Growable() for name in ("t", "odo", "lat", "lon", "h")}
        self._s_q = _Growable((4,))
        self._s_epoch = _Growable((), np.int32)
        self.marker_residuals: dict[str, Array] = {}

    def __len__(self) -> int:
        return len(self._packed)

    @property
    def _rows(self) -> _Chunks:
        """The packed rows, every epoch added so far packed."""
        if self._packing is not None:
            job, self._packing = self._packing, None
            job.result()  # a failed pack raises here
        return self._packed

    # ------------------------------------------------------------------ filling
    def add_epochs(
        self,
        states: Array,
        *,
        dx: Array,
        P_upd: Array,
        P_pred: Array,
        phi: Array,
        x_upd: Array | None = None,
        end_offset: Array | None = None,
    ) -> None:
        """B epochs: states (B, SV_SIZE); dx, x_upd, end_offset (B, n); P_upd, P_pred, phi
        (B, n, n) (rows of phi outside :func:`phi_rows` must be the identity's). x_upd and
        end_offset only for a recording about a reference.

        The covariances are packed in a second thread while the caller goes on (the packing
        kernel releases the GIL), after the previous call's: the caller must leave this
        call's P_upd, P_pred and phi as they are until its next call (the engine alternates
        two output buffers), or until it reads the recording."""
        claims = self._rows.claim(len(states))

        def pack() -> None:
            for a, b, out in claims:
                self.format.pack(out, P_upd[a:b], P_pred[a:b], phi[a:b])

        if self._packer is None:
            self._packer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="pipe-nav-pack")
            weakref.finalize(self, self._packer.shutdown, wait=False)
        self._packing = self._packer.submit(pack)
        self._states.extend(states)
        self._dx.extend(dx)
        if self.linearized:
            assert self._x_upd is not None and self._end_offset is not None
            self._x_upd.extend(x_upd)
            self._end_offset.extend(end_offset)

    def add_epoch(self, state: Array, **arrays: Array | None) -> None:
        """One epoch: :meth:`add_epochs` with (SV_SIZE,), (n,) and (n, n) arrays (copied:
        the caller may go on changing them)."""
        self.add_epochs(
            np.array(state, dtype=np.float64)[None],
            **{k: None if v is None else np.array(v, dtype=np.float64)[None]
               for k, v in arrays.items()},
        )  # fmt: skip

    def add_blocks(
        self,
        ends: NDArray[np.int64],
        t: Array,
        odo: Array,
        lat: Array,
        lon: Array,
        h: Array,
        q: Array,
    ) -> None:
        """The nominal at the IMU samples of the blocks of the last len(ends) epochs: block e
        is samples ends[e - 1] + 1 .. ends[e] (0 .. ends[0] for the first) of t (s), the raw
        odometer odo (m), lat, lon (rad), h (m) and q (N, 4) [x, y, z, w] base_link -> ENU.
        Of each block, every m-th sample counted back from its last is kept, m the number of
        mean sample intervals that fit in SAMPLE_SPACING_S (at least 1)."""
        ends = np.asarray(ends, dtype=np.int64)
        if not len(ends):
            return
        starts = np.r_[0, ends[:-1] + 1]
        length = ends - starts + 1
        m = np.ones(len(ends), dtype=np.int64)
        if SAMPLE_SPACING_S > 0.0:
            span = t[ends] - t[starts]
            long = (length > 1) & (span > 0.0)
            m[long] = np.maximum(
                1, (SAMPLE_SPACING_S * (length[long] - 1) / span[long] + 1e-6).astype(np.int64)
            )
        block = np.repeat(np.arange(len(ends)), length)
        i = np.arange(ends[-1] + 1)
        keep = i[(ends[block] - i) % m[block] == 0]
        for name, x in zip(("t", "odo", "lat", "lon", "h"), (t, odo, lat, lon, h)):
            self._s[name].extend(x[keep])
        self._s_q.extend(q[keep])
        first = len(self) - len(ends)
        self._s_epoch.extend((first + block[keep]).astype(np.int32))

    # ------------------------------------------------------------------ per epoch
    @property
    def states(self) -> Array:
        return self._states.data

    @property
    def t(self) -> Array:
        return self._states.data[:, 0]

    @property
    def lin(self) -> Array:
        return self._reference[: len(self.states)] if self._reference is not None else self.states

    @property
    def dx(self) -> Array:
        return self._dx.data

    @property
    def x_upd(self) -> Array:
        return self._x_upd.data if self._x_upd is not None else np.zeros_like(self.dx)

    @property
    def end_offset(self) -> Array:
        return self._end_offset.data if self._end_offset is not None else self.dx

    def P_upd(self, k: int) -> Array:
        """Updated covariance of epoch k (n, n)."""
        return self.format.covariances(self._rows.rows([k]), "upd")[0]

    def P_pred(self, k: int) -> Array:
        """Predicted covariance of epoch k (n, n) (the alignment's: its P_upd)."""
        return self.format.covariances(self._rows.rows([k]), "pred")[0]

    def phi(self, k: int) -> Array:
        """Transition from epoch k-1 to k (n, n) (the alignment's: the identity)."""
        return self.format.transitions(self._rows.rows([k]))[0]

    def covariances(self, ks: Array, which: str = "upd") -> Array:
        """P_upd ("upd") or P_pred ("pred") of the epochs ks (B, n, n)."""
        return self.format.covariances(self._rows.rows(ks), which)

    def variances(self) -> Array:
        """The diagonals of P_upd (K, n)."""
        out = np.empty((len(self), self.layout.n))
        for i in range(self._rows.n_chunks):
            rows = self._rows.chunk(i)
            out[i * CHUNK_EPOCHS : i * CHUNK_EPOCHS + len(rows)] = self.format.variances(rows)
        return out

    def rts_chunks(self) -> Iterator[tuple[int, Array]]:
        """(first epoch, packed rows (C, format.width)) from the last chunk to the first, as
        :func:`pipe_nav_core.smooth.rts.rts_packed` reads them."""
        for i in range(self._rows.n_chunks - 1, -1, -1):
            yield i * CHUNK_EPOCHS, self._rows.chunk(i)

    # ------------------------------------------------------------------ per sample
    @property
    def s_t(self) -> Array:
        return self._s["t"].data

    @property
    def s_odo(self) -> Array:
        return self._s["odo"].data

    @property
    def s_lat(self) -> Array:
        return self._s["lat"].data

    @property
    def s_lon(self) -> Array:
        return self._s["lon"].data

    @property
    def s_h(self) -> Array:
        return self._s["h"].data

    @property
    def s_q(self) -> Array:
        return self._s_q.data

    @property
    def s_epoch(self) -> NDArray[np.int32]:
        return self._s_epoch.data

    def close(self) -> None:
        """Free the packed rows (the covariances and transitions) and remove their temporary
        files (also done when the recording is garbage collected); the per-epoch and
        per-sample arrays stay."""
        self._rows.close()
        if self._packer is not None:
            self._packer.shutdown(wait=True)
            self._packer = None
