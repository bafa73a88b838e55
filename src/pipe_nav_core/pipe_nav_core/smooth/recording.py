"""What the smoothers need from a forward filter pass, in compact contiguous storage.

Per epoch (k = 0 is the alignment): the filter's estimate and its linearization point as flat
state vectors (:data:`pipe_nav_core.model.state.SV_SIZE`), the mean error state, and one packed row
of covariances and transition for the RTS smoother (:class:`pipe_nav_core.smooth.rts.EpochRows`).
Per IMU sample: the nominal trajectory the corrections are applied to.

The packed rows are the bulk (some 15 kB per epoch with 38 error states): they are kept in
chunks of CHUNK_EPOCHS epochs, and beyond RECORDING_BUDGET_BYTES the oldest chunks go to a
temporary directory, removed when the recording is closed or garbage collected. The smoother
reads them back from the last to the first (:meth:`Recording.rts_chunks`). The chunked storage
itself is :mod:`pipe_nav_core.smooth.chunks`.
"""

from __future__ import annotations

import weakref
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.model.state import SV_SIZE, Layout
from pipe_nav_core.smooth.chunks import CHUNK_EPOCHS, Chunks, Growable
from pipe_nav_core.smooth.rts import EpochRows

Array = NDArray[np.float64]

# bytes of packed rows a recording keeps in memory before its oldest chunks spill: the 10 km
# line's (four chunks, 240 MB, at a tactical IMU's 2.5 Hz smoothing epochs) stay whole, so its
# RTS reads nothing back and no read buffers are written (0.3-0.5 s, and a lower peak)
RECORDING_BUDGET_BYTES = 256 * 2**20
# the per-sample nominal is thinned to about one sample per this many seconds, never sparser
# (0: every IMU sample): the centreline is resampled every 0.5 m of chainage for the products
SAMPLE_SPACING_S = 0.02


def phi_rows(layout: Layout) -> Array:
    """The rows of the error-state transition that can differ from the identity: attitude,
    velocity and position (the only nonzero rows of the system matrix; process.discretize_k)
    the odometer reading errors (shifted each epoch) and the section direction (restarted
    at each straight section's start)."""
    rows = np.arange(layout.pos.stop)
    for block in (layout.odoq, layout.dir):
        if block is not None:
            rows = np.r_[rows, np.arange(block.start, block.stop)]
    return rows


def constant_states(layout: Layout) -> Array:
    """The error states that are random constants: the odometer boresight and the IMU error
    matrices, whose transition rows are the identity's and whose process noise
    (process.process_noise_k: 1e-8 rad/sqrt(s), 1e-9 /sqrt(s)) only keeps them from being
    exactly known. The RTS takes their gain columns as unit vectors wherever the stored
    covariances bear it out (smooth.rts.EpochRows, rts.CONSTANT_GROWTH)."""
    blocks = (layout.bore, layout.gm, layout.am)
    return np.concatenate([np.arange(b.start, b.stop) for b in blocks if b is not None])


class Recording:
    """What the smoothers need from a forward pass (see the module docstring).

    Per epoch k (arrays with K rows): ``states`` (K, SV_SIZE) the filter's estimate after the update
    (flat, :meth:`NavState.vector`; ``t`` its times, s); ``lin`` the linearization point (the
    estimate itself for the ordinary EKF, the reference state when the filter runs about a reference
    trajectory); ``x_upd`` (K, n) the filter's mean error state relative to it (zero for the EKF);
    ``dx`` (K, n) updated minus predicted mean error state (what an RTS smoother carries back);
    ``end_offset`` (K, 6) lin (-) the nominal at the end of the block (the correction that moves the
    per-sample nominal onto the linearization point; dx for the EKF), its columns ``pose``
    (position, attitude) only; the predicted and updated covariances and Phi from k-1 to k
    (:meth:`P_upd`, :meth:`P_pred`, :meth:`phi`, packed: :meth:`rts_chunks`).
    Per kept IMU sample: ``s_t`` s, ``s_odo`` raw odometer distance m, nominal ``s_lat``,
    ``s_lon`` rad, ``s_h`` m, ``s_q`` [x, y, z, w] base_link -> ENU, and ``s_epoch``: the
    epoch whose block the sample belongs to (the block of epoch k starts at lin[k - 1]).

    reference: the trajectory (K, SV_SIZE) the filter runs about, if any: it is lin (not
    copied), and x_upd and end_offset are stored; without one they follow from states and dx.

    centreline_only (a pass about a reference whose only use is its centreline: the graph
    smoother's): of each epoch only its time ``t``, the ``pose`` columns of x_upd
    (:attr:`x_upd_pose`) and end_offset are kept; no covariances are packed and ``states``,
    ``dx``, ``x_upd`` and the covariances are not there (at 100 km some 0.45 GB and 8 GB of
    packed rows written to disk less).
    """

    def __init__(
        self,
        layout: Layout,
        *,
        reference: Array | None = None,
        ram_budget: int = RECORDING_BUDGET_BYTES,
        centreline_only: bool = False,
    ) -> None:
        self.layout = layout
        self._reference = reference
        linearized = self.linearized = reference is not None
        if centreline_only and not linearized:
            raise ValueError("a recording for the centreline only is of a pass about a reference")
        self.centreline_only = centreline_only
        self.format = EpochRows(layout.n, phi_rows(layout), constant_states(layout))
        self._packed = Chunks(self.format.width, ram_budget, read_back=True)  # by the RTS
        self._packer: ThreadPoolExecutor | None = None
        self._packing: Future[None] | None = None
        n = layout.n
        self.pose = np.r_[layout.pos, layout.att]  # the columns the centreline is made of
        # a pass about a reference has an epoch per reference state (room reserved up front)
        rows = len(reference) if reference is not None else 256
        whole = not centreline_only
        self._states = Growable((SV_SIZE,) if whole else (), capacity=rows)  # else t only
        self._dx = Growable((n,), capacity=rows) if whole else None
        self._pose_var = Growable((len(self.pose),), capacity=rows) if whole else None
        x_cols = n if whole else len(self.pose)
        self._x_upd = Growable((x_cols,), capacity=rows) if linearized else None
        self._end_offset = Growable((len(self.pose),), capacity=rows) if linearized else None
        self._s = {name: Growable() for name in ("t", "odo", "lat", "lon", "h")}
        self._s_q = Growable((4,))
        self._s_epoch = Growable((), np.int32)
        self.marker_residuals: dict[str, Array] = {}

    def __len__(self) -> int:
        return len(self._states.data) if self.centreline_only else len(self._packed)

    @property
    def _rows(self) -> Chunks:
        """The packed rows, every epoch added so far packed."""
        self._whole("covariances")
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
        if self.centreline_only:
            assert x_upd is not None and end_offset is not None
            self._states.extend(states[:, 0])
            self._x_upd.extend(x_upd[:, self.pose])  # type: ignore[union-attr]
            self._end_offset.extend(end_offset[:, self.pose])  # type: ignore[union-attr]
            return
        claims = self._rows.claim(len(states))

        def pack() -> None:
            for a, b, out in claims:
                self.format.pack(out, P_upd[a:b], P_pred[a:b], phi[a:b])

        if self._packer is None:
            self._packer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="pipe-nav-pack")
            weakref.finalize(self, self._packer.shutdown, wait=False)
        self._packing = self._packer.submit(pack)
        self._states.extend(states)
        self._dx.extend(dx)  # type: ignore[union-attr]
        self._pose_var.extend(P_upd[:, self.pose, self.pose])  # type: ignore[union-attr]
        if self.linearized:
            assert self._x_upd is not None and self._end_offset is not None
            self._x_upd.extend(x_upd)
            self._end_offset.extend(end_offset[:, self.pose])

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
        self._whole("states")
        return self._states.data

    @property
    def t(self) -> Array:
        """(K,) the epochs' times, s."""
        return self._states.data if self.centreline_only else self._states.data[:, 0]

    def _whole(self, what: str) -> None:
        """Raise when ``what`` is not kept (a recording for the centreline only)."""
        if self.centreline_only:
            raise ValueError(f"a recording for the centreline only has no {what}")

    @property
    def lin(self) -> Array:
        if self._reference is None:
            return self.states
        return self._reference[: len(self._states.data)]  # (len(self) is 0 once closed)

    @property
    def dx(self) -> Array:
        self._whole("dx")
        assert self._dx is not None
        return self._dx.data

    @property
    def x_upd(self) -> Array:
        self._whole("x_upd (x_upd_pose has its pose columns)")
        if self._x_upd is not None:
            return self._x_upd.data
        shape = (len(self._states.data), self.layout.n)
        return np.broadcast_to(np.zeros(self.layout.n), shape)  # zeros, read-only

    @property
    def x_upd_pose(self) -> Array:
        """(K, 6) the columns ``pose`` (position m, attitude rad) of x_upd (a copy unless the
        recording is for the centreline only)."""
        if self.centreline_only:
            assert self._x_upd is not None
            return self._x_upd.data
        return self.x_upd[:, self.pose]

    @property
    def end_offset(self) -> Array:
        """(K, 6) the columns ``pose`` (position m, attitude rad) of end_offset."""
        return self._end_offset.data if self._end_offset is not None else self.dx[:, self.pose]

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

    def pose_variances(self) -> Array:
        """(K, 6) the variances of the ``pose`` columns (position m^2, attitude rad^2) of
        P_upd, kept as the epochs come: the forward trajectory's sigmas without reading back
        the packed rows (at 10 km 0.8 GB from the spill files)."""
        self._whole("pose variances")
        assert self._pose_var is not None
        return self._pose_var.data

    def variances(self) -> Array:
        """The diagonals of P_upd (K, n)."""
        out = np.empty((len(self), self.layout.n))
        for i in range(self._rows.n_chunks):
            rows = self._rows.chunk(i)
            out[i * CHUNK_EPOCHS : i * CHUNK_EPOCHS + len(rows)] = self.format.variances(rows)
        return out

    def rts_chunks(self) -> Iterator[tuple[int, Array]]:
        """(first epoch, packed rows (C, format.width)) from the last chunk to the first, as
        :func:`pipe_nav_core.smooth.rts.rts_packed` reads them. The chunk before is read
        (back from its spill file) in a second thread while the caller works on this one:
        the caller holds this chunk and the one after it, the read takes the third of the
        READ_BUFFERS."""
        rows = self._rows
        if not rows.n_chunks:
            return
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="pipe-nav-read") as pool:
            ahead = pool.submit(rows.chunk, rows.n_chunks - 1)
            for i in range(rows.n_chunks - 1, -1, -1):
                chunk = ahead.result()
                if i:
                    ahead = pool.submit(rows.chunk, i - 1)
                yield i * CHUNK_EPOCHS, chunk

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

    def keep_for_centreline(self) -> None:
        """Keep only what :func:`~pipe_nav_core.smooth.centreline.smoothed_centreline` reads
        (a recording about a reference after its smoothing, whose centreline is the last use:
        the last pass), as a recording made ``centreline_only``: the covariances, dx, the
        states but their times, x_upd but its pose columns and s_odo go (at 100 km 0.35 GB).
        Nothing is done to a recording not about a reference."""
        if not self.linearized or self.centreline_only:
            return
        self.close()
        t, x_pose = self.t.copy(), self.x_upd_pose  # (x_upd_pose: a copy)
        self._states, self._dx, self._pose_var = Growable(capacity=1), None, None
        self._x_upd = Growable((len(self.pose),), capacity=1)
        self._states.extend(t)
        self._x_upd.extend(x_pose)
        self._s["odo"] = Growable(capacity=1)
        self.centreline_only = True

    def take_nominal(self) -> tuple[Array, Array, Array, Array, Array]:
        """The per-sample nominal (s_t, s_lat, s_lon, s_h, s_q), given up by the recording (its
        arrays are empty after; s_odo and s_epoch stay): the caller may write over them. The
        smoothed centreline is made in them, so that the nominal and the centreline are not
        both in memory (at 100 km 0.16 GB)."""
        names = ("t", "lat", "lon", "h")
        out = tuple(self._s[name].data for name in names) + (self._s_q.data,)
        for name in names:
            self._s[name] = Growable(capacity=1)
        self._s_q = Growable((4,), capacity=1)
        return out  # type: ignore[return-value]

    def reserve(self, epochs: int, samples: int) -> None:
        """Room for this many epochs and kept samples, the pass's expected counts (a pass that
        has more still records them all): the arrays are not grown by doubling, which holds
        the old array beside one twice its size (at 100 km 0.5 GB for a moment). The packed
        rows of a pass that will spill keep only the chunks' own budget in memory
        (Chunks.expect)."""
        if not self.centreline_only:
            self._packed.expect(epochs)
        for g in (self._states, self._dx, self._pose_var, self._x_upd, self._end_offset):
            if g is not None:
                g.reserve(epochs)
        for g in (*self._s.values(), self._s_q, self._s_epoch):
            g.reserve(samples)

    def trim(self) -> None:
        """End of the pass: the per-epoch and per-sample arrays let go of the room they had
        reserved to grow (up to half of each; at 100 km some 0.3 GB)."""
        for g in (self._states, self._dx, self._pose_var, self._x_upd, self._end_offset,
                  *self._s.values(), self._s_q, self._s_epoch):  # fmt: skip
            if g is not None:
                g.trim()

    def close(self) -> None:
        """Free the packed rows (the covariances and transitions) and remove their temporary
        files (also done when the recording is garbage collected), the pose variances, and
        ``dx`` (only the RTS smoother reads it; of the ordinary EKF's, end_offset, its pose
        columns, are kept: at 100 km 0.13 GB less); the other per-epoch and the per-sample
        arrays stay."""
        if self._packing is not None:  # the last pack ends first
            job, self._packing = self._packing, None
            job.result()
        self._packed.close()  # (none packed for a recording for the centreline only)
        if self._dx is not None and len(self._dx.data):
            if not self.linearized:  # the EKF's end_offset is dx
                self._end_offset = Growable((len(self.pose),), capacity=len(self._dx.data))
                self._end_offset.extend(self._dx.data[:, self.pose])
            self._dx = Growable((self.layout.n,), capacity=1)
        if self._pose_var is not None:
            self._pose_var = Growable((len(self.pose),), capacity=1)
        if self._packer is not None:
            self._packer.shutdown(wait=True)
            self._packer = None
