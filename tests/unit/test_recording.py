"""The compact Recording and its chunked storage (smooth.chunks): packed covariances and
transitions read back exactly, from memory or spilled to disk, and the RTS over its chunks
equals the RTS over the full matrices."""

import gc
import os

import numpy as np
import pytest
from pipe_nav_core.model.state import SV_SIZE, Layout
from pipe_nav_core.smooth import chunks, recording
from pipe_nav_core.smooth.recording import Recording, constant_states, phi_rows
from pipe_nav_core.smooth.rts import rts, rts_packed


def _epochs(layout: Layout, K: int, seed: int = 0, inflate: dict[int, float] | None = None):
    """K random epochs of consistent (positive-definite) covariances and transitions, the
    random constants (recording.constant_states) without process noise; inflate: epoch ->
    factor of its predicted covariance (a marker epoch's inflation)."""
    rng = np.random.default_rng(seed)
    n = layout.n
    rows = phi_rows(layout)
    out = []
    P = np.eye(n)
    for _ in range(K):
        phi = np.eye(n)
        phi[rows] += rng.normal(size=(len(rows), n)) * 0.05
        a = rng.normal(size=(n, n)) * 0.05
        Q = a @ a.T + 1e-3 * np.eye(n)
        Q[constant_states(layout)] = 0.0
        Q[:, constant_states(layout)] = 0.0
        P_pred = (phi @ P @ phi.T + Q) * (inflate or {}).get(len(out), 1.0)
        P = 0.9 * P_pred  # a stand-in for an update
        out.append((rng.normal(size=SV_SIZE), rng.normal(size=n), P.copy(), P_pred, phi))
    return out


@pytest.mark.parametrize("budget", [recording.RECORDING_BUDGET_BYTES, 0])
def test_recording_reads_back_what_was_stored(monkeypatch, budget):
    """With a budget of 0 all but the two newest chunks go to disk; the values are the same,
    and the temporary directory goes when the recording is closed."""
    monkeypatch.setattr(chunks, "CHUNK_EPOCHS", 16)
    monkeypatch.setattr(recording, "CHUNK_EPOCHS", 16)
    layout = Layout("ins", gyro_errors=True)
    epochs = _epochs(layout, 75)
    rec = Recording(layout, ram_budget=budget)
    for state, dx, P_upd, P_pred, phi in epochs:
        rec.add_epoch(state, dx=dx, P_upd=P_upd, P_pred=P_pred, phi=phi)
    rec._rows.flush()  # the spilled chunks are read back from their files
    spill_dir = rec._rows._dir
    assert (spill_dir is not None) == (budget == 0)
    assert len(rec) == 75
    np.testing.assert_array_equal(rec.states, [x[0] for x in epochs])
    for k in (0, 17, 74, 3):
        _, _, P_upd, P_pred, phi = epochs[k]
        np.testing.assert_array_equal(rec.P_upd(k), np.triu(P_upd) + np.triu(P_upd, 1).T)
        np.testing.assert_array_equal(rec.P_pred(k), np.triu(P_pred) + np.triu(P_pred, 1).T)
        np.testing.assert_array_equal(rec.phi(k), phi)
    np.testing.assert_array_equal(rec.variances(), [np.diag(x[2]) for x in epochs])
    assert rec.pose_variances().tobytes() == rec.variances()[:, rec.pose].tobytes()
    e, var = rts_packed(rec.rts_chunks(), rec.dx, rec.format)
    P_upd, P_pred, phi = ([x[i] for x in epochs] for i in (2, 3, 4))
    e_ref, P_ref = rts(P_upd, P_pred, phi, rec.dx)
    np.testing.assert_allclose(e, e_ref, rtol=0, atol=1e-12)
    # the packed RTS takes the random constants' gain columns as exact unit vectors: the
    # same smoother, to round-off
    np.testing.assert_allclose(var, np.diagonal(P_ref, axis1=1, axis2=2), rtol=1e-10)
    e_some, var_some = rts_packed(rec.rts_chunks(), rec.dx, rec.format, var_cols=[5, 0, 2])
    assert e_some.tobytes() == e.tobytes() and var_some.tobytes() == var[:, [5, 0, 2]].tobytes()
    rec.close()
    if spill_dir is not None:
        assert not os.path.exists(spill_dir)


@pytest.mark.parametrize("inflate", [{}, {10: 3.0, 25: 1.0 + 1e-4, 39: 2.0}])
def test_the_rts_takes_the_constants_gain_columns_as_unit_where_they_are(inflate):
    """The packed RTS takes the random constants' gain columns as unit vectors (their
    predicted covariance is their updated one) and solves the whole gain of an epoch whose
    predicted covariance the filter inflated: the same smoother as over the full matrices,
    to round-off, either way."""
    layout = Layout("ins", gyro_errors=True, accel_errors=True)
    assert len(constant_states(layout)) == 20  # the boresight and the IMU error matrices
    epochs = _epochs(layout, 40, seed=3, inflate=inflate)
    rec = Recording(layout)
    for state, dx, P_upd, P_pred, phi in epochs:
        rec.add_epoch(state, dx=dx, P_upd=P_upd, P_pred=P_pred, phi=phi)
    e, P = rts_packed(rec.rts_chunks(), rec.dx, rec.format, full=True)
    e_ref, P_ref = rts(*([x[i] for x in epochs] for i in (2, 3, 4)), rec.dx)
    np.testing.assert_allclose(e, e_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(P, P_ref, rtol=0, atol=1e-12)
    rec.close()


def test_chunks_read_ahead_leave_the_ones_the_smoother_holds(monkeypatch):
    """rts_chunks reads the chunk before in a second thread while the caller works on this
    one: every chunk comes in order with its rows, and the one the caller still holds from
    before (the RTS smoother's next_row and last piece) is not overwritten by the read."""
    monkeypatch.setattr(chunks, "CHUNK_EPOCHS", 4)
    monkeypatch.setattr(recording, "CHUNK_EPOCHS", 4)
    layout = Layout("dr")
    epochs = _epochs(layout, 30)
    rec = Recording(layout, ram_budget=0)
    for state, dx, P_upd, P_pred, phi in epochs:
        rec.add_epoch(state, dx=dx, P_upd=P_upd, P_pred=P_pred, phi=phi)
    expected = np.concatenate([rec._rows.chunk(i).copy() for i in range(rec._rows.n_chunks)])
    assert rec._rows._dir is not None  # spilled: read back from files
    firsts, held = [], None
    for k0, rows in rec.rts_chunks():
        firsts.append(k0)
        if held is not None:
            np.testing.assert_array_equal(held[1], expected[held[0] : held[0] + len(held[1])])
        np.testing.assert_array_equal(rows, expected[k0 : k0 + len(rows)])
        held = (k0, rows)
    assert firsts == list(range(28, -1, -4))
    rec.close()


def test_spilled_chunks_go_with_the_recording(monkeypatch):
    monkeypatch.setattr(chunks, "CHUNK_EPOCHS", 4)
    monkeypatch.setattr(recording, "CHUNK_EPOCHS", 4)
    layout = Layout("dr")
    rec = Recording(layout, ram_budget=0)
    for state, dx, P_upd, P_pred, phi in _epochs(layout, 20):
        rec.add_epoch(state, dx=dx, P_upd=P_upd, P_pred=P_pred, phi=phi)
    rec._rows.flush()
    spill_dir = rec._rows._dir
    assert spill_dir is not None and os.listdir(spill_dir)
    del rec
    gc.collect()
    assert not os.path.exists(spill_dir)


def test_transition_rows_outside_the_stored_ones_must_be_identity():
    layout = Layout("ins")
    rec = Recording(layout)
    phi = np.eye(layout.n)
    phi[layout.bg.start, layout.pos.start] = 1e-3  # a row the recording does not keep
    with pytest.raises(ValueError, match="identity"):
        rec.add_epoch(np.zeros(SV_SIZE), dx=np.zeros(layout.n), P_upd=phi, P_pred=phi, phi=phi)
        rec.variances()  # packed in a second thread: its error comes with the next read


def test_an_epoch_is_stored_as_it_was_given_while_the_caller_goes_on():
    """The covariances are packed in a second thread: add_epoch's arrays are the caller's to
    change at once (the engine updates its covariance in place right after the alignment)."""
    layout = Layout("ins", gyro_errors=True)
    epochs = _epochs(layout, 40)
    rec = Recording(layout)
    given = []
    for state, dx, P_upd, P_pred, phi in epochs:
        given.append(P_upd.copy())
        rec.add_epoch(state, dx=dx, P_upd=P_upd, P_pred=P_pred, phi=phi)
        P_upd *= 3.0  # as the filter's next prediction would
    for k in (0, 21, 39):
        P = given[k]
        np.testing.assert_array_equal(rec.P_upd(k), np.triu(P) + np.triu(P, 1).T)


def _writes_held(monkeypatch):
    """Chunks' spill writes wait until the returned event is set (10 s at most); the spare
    pool emptied."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    held = threading.Event()

    class SlowWriter(ThreadPoolExecutor):
        def submit(self, fn, /, *args, **kwargs):  # the write waits until the test lets it
            return super().submit(lambda: (held.wait(10.0), fn(*args, **kwargs)))

    monkeypatch.setattr(chunks, "ThreadPoolExecutor", SlowWriter)
    chunks.drop_spare()
    return held


def test_a_chunk_asked_for_while_its_file_is_written_stays_whole(monkeypatch):
    """A chunk being spilled is read back whole, and its rows stay as they were while the
    caller reads the chunk before it: its array returns to the pool only once its file is
    complete, and reading waits for that (else the next read could refill it)."""
    import threading
    import time

    held = _writes_held(monkeypatch)
    width, n = 3, 2 + chunks.PENDING_WRITES  # as many spilled as may wait for the disk
    rows = chunks.Chunks(width, budget=0)  # two chunks in memory, older ones spill
    for k in range(n):
        for _a, _b, view in rows.claim(chunks.CHUNK_EPOCHS):
            view[:] = k  # chunk k's rows all hold k
    threading.Timer(0.2, held.set).start()
    last_spilled = n - 3
    got = rows.chunk(last_spilled)  # asked for while its write is held back
    time.sleep(0.5)  # the writes are done: their arrays are spare
    before = rows.chunk(last_spilled - 1)  # read back into a spare array
    assert np.all(got == last_spilled) and np.all(before == last_spilled - 1)
    rows.close()


def test_a_recording_faster_than_its_disk_waits_for_it(monkeypatch):
    """Chunks whose files are written more slowly than they are filled: at most
    PENDING_WRITES wait in memory for the disk and the next spill waits for the oldest (before,
    they queued without bound: the 100 km line's peak rose by 0.9 GB on a slow disk); every
    row comes back as written."""
    import threading

    held = _writes_held(monkeypatch)
    n, per = 10, 4
    rows = chunks.Chunks(2, budget=0, rows=per)  # two chunks in memory, older ones spill
    waiting: list[int] = []

    def fill() -> None:
        for k in range(n * per):
            for _a, _b, view in rows.claim(1):
                view[:] = k
            waiting.append(len(rows._writes))

    filler = threading.Thread(target=fill)
    filler.start()
    try:
        filler.join(1.0)
        assert filler.is_alive()  # held at the spill after PENDING_WRITES unwritten ones
        assert len(rows._writes) == chunks.PENDING_WRITES
        assert len(waiting) < (2 + chunks.PENDING_WRITES + 1) * per
    finally:
        held.set()
    filler.join(10.0)
    assert not filler.is_alive() and max(waiting) <= chunks.PENDING_WRITES
    got = rows.rows(np.arange(n * per))
    assert np.array_equal(got, np.repeat(np.arange(n * per, dtype=float)[:, None], 2, axis=1))
    rows.close()


def test_reading_back_in_any_order_keeps_the_last_chunks_asked_for():
    """The RTS pass reads the chunks from the last back, holding the one it is at while it asks
    for the one before; a forward read (the variances) may have left other chunks in the read
    buffers. A buffer is reused only for the chunk asked for least recently, so the one the
    caller holds is never refilled under it."""
    chunks.drop_spare()
    rows = chunks.Chunks(2, budget=0)  # two chunks in memory, the older ones spill
    n = 7
    for k in range(n):
        for _a, _b, view in rows.claim(chunks.CHUNK_EPOCHS):
            view[:] = k
    for i in range(n):  # forward, as Recording.variances reads them
        assert np.all(rows.chunk(i) == i)
    held = None
    for i in range(n - 1, -1, -1):  # backward, as rts_packed reads them
        here = rows.chunk(i)
        if held is not None:
            assert np.all(held == i + 1), f"chunk {i + 1} refilled while held"
        assert np.all(here == i)
        held = here
    rows.close()


def test_a_finished_pass_lets_go_of_its_spare_room():
    """trim() keeps every row and drops the room reserved to grow; a pass about a reference
    reserves a row per reference state, and close() lets its dx go (only RTS reads it)."""
    layout = Layout("ins", gyro_errors=True)
    epochs = _epochs(layout, 300)
    rec = Recording(layout)
    for state, dx, P_upd, P_pred, phi in epochs:
        rec.add_epoch(state, dx=dx, P_upd=P_upd, P_pred=P_pred, phi=phi)
    assert len(rec._states._a) == 512  # grown by doubling
    rec.trim()
    assert len(rec._states._a) == 300
    np.testing.assert_array_equal(rec.states, [x[0] for x in epochs])
    np.testing.assert_array_equal(rec.dx, [x[1] for x in epochs])
    assert not rec.x_upd.any() and rec.x_upd.shape == (300, layout.n)  # no copy: a view
    rec.close()
    assert len(rec.dx) == 0  # the EKF's dx: its end_offset (pose columns) kept
    assert rec.x_upd.shape == (300, layout.n) and len(rec.lin) == 300

    ref = np.array([x[0] for x in epochs])
    about = Recording(layout, reference=ref)
    assert len(about._states._a) == len(about._x_upd._a) == 300
    for state, dx, P_upd, P_pred, phi in epochs:
        about.add_epoch(state, dx=dx, P_upd=P_upd, P_pred=P_pred, phi=phi, x_upd=dx,
                        end_offset=dx)  # fmt: skip
    assert len(about._states._a) == 300  # no growing
    about.close()
    assert len(about.dx) == 0 and len(about.lin) == 300
    pose = np.r_[layout.pos, layout.att]  # of end_offset, only what the centreline needs
    np.testing.assert_array_equal(about.end_offset, [x[1][pose] for x in epochs])
    np.testing.assert_array_equal(rec.end_offset, [x[1][pose] for x in epochs])


def _filled(layout: Layout, epochs, **kw) -> Recording:
    """A recording about a reference of the given epochs, with five IMU samples a block."""
    ref = np.array([x[0] for x in epochs])
    ref[:, 0] = np.arange(len(epochs)) * 0.1  # the epochs' times, s
    rec = Recording(layout, reference=ref, **kw)
    rng = np.random.default_rng(7)
    for k, (_, dx, P_upd, P_pred, phi) in enumerate(epochs):
        rec.add_epoch(ref[k], dx=dx, P_upd=P_upd, P_pred=P_pred, phi=phi, x_upd=2.0 * dx,
                      end_offset=-dx)  # fmt: skip
        if k:
            t = (k - 1) * 0.1 + np.arange(1, 6) * 0.02
            q = rng.normal(size=(5, 4))
            rec.add_blocks(np.array([4]), t, np.cumsum(rng.random(5)), 0.7 + 1e-7 * rng.random(5),
                           0.2 + 1e-7 * rng.random(5), 100.0 + rng.random(5),
                           q / np.linalg.norm(q, axis=1)[:, None])  # fmt: skip
    return rec


def _centreline_before(rec: Recording, e: np.ndarray, var: np.ndarray):
    """smoothed_centreline as it was before it was made in the recording's own arrays (the
    columns it returned: lat, lon, h, q, sigma_enu, sigma_att), for comparison."""
    from pipe_nav_core.geo import attitude as att
    from pipe_nav_core.geo import earth

    cols = rec.pose
    d_lin = rec.x_upd[:, cols] + e[:, cols]
    d_end = d_lin + rec.end_offset
    t_ep, t, k = rec.t, rec.s_t, rec.s_epoch
    frac = (t - t_ep[k - 1]) / np.maximum(t_ep[k] - t_ep[k - 1], 1e-12)
    w0, w1 = (1.0 - frac)[:, None], frac[:, None]
    corr = w0 * d_lin[k - 1] + w1 * d_end[k]
    dlat, dlon, dh = earth.enu_to_geodetic_increment(corr[:, :3], rec.s_lat, rec.s_h)
    q = att.quat_normalize(att.quat_mul(att.quat_from_rotvec(corr[:, 3:]), rec.s_q))
    var_s = w0 * var[k - 1] + w1 * var[k]
    sig = np.sqrt(np.maximum(var_s, 0.0))
    return rec.s_lat + dlat, rec.s_lon + dlon, rec.s_h + dh, q, sig[:, :3], sig[:, 3:]


def test_the_centreline_is_made_in_the_recordings_nominal():
    """smoothed_centreline overwrites the recording's per-sample nominal with the centreline
    (the recording has none after) and gives the bytes it gave when it made new arrays; a
    recording for the centreline only (the graph's) keeps what it reads, the same bytes, and
    packs no covariances."""
    from pipe_nav_core.smooth.centreline import smoothed_centreline

    layout = Layout("ins", gyro_errors=True)
    epochs = _epochs(layout, 40)
    whole = _filled(layout, epochs)
    only = _filled(layout, epochs, centreline_only=True)
    narrowed = _filled(layout, epochs)  # the last pass's, once smoothed
    narrowed.keep_for_centreline()
    assert narrowed.centreline_only and len(narrowed) == 40 and len(narrowed.s_odo) == 0
    rng = np.random.default_rng(3)
    e = rng.normal(size=(40, layout.n)) * 1e-3
    var = rng.random((40, 6)) * 1e-4
    before = _centreline_before(whole, e, var)
    assert len(only) == len(whole) == 40 and len(only._packed) == 0
    for name in ("t", "x_upd_pose", "end_offset", "s_t", "s_epoch", "s_lat", "s_q"):
        assert getattr(only, name).tobytes() == getattr(whole, name).tobytes(), name
    for name in ("states", "dx", "x_upd"):
        with pytest.raises(ValueError, match="centreline only"):
            getattr(only, name)
    with pytest.raises(ValueError, match="centreline only"):
        only.P_upd(0)
    s_odo = whole.s_odo.copy()
    for name in ("t", "x_upd_pose", "end_offset", "s_t", "s_epoch", "s_lat", "s_q"):
        assert getattr(narrowed, name).tobytes() == getattr(whole, name).tobytes(), name
    got = [smoothed_centreline(r, e[:, r.pose], var) for r in (whole, only, narrowed)]
    for c in got:
        cols = (c.lat, c.lon, c.h, c.quat_nb, c.sigma_enu, c.sigma_att)
        for a, b in zip(cols, before):
            assert a.tobytes() == b.tobytes()
    assert len(whole.s_t) == len(whole.s_lat) == len(whole.s_q) == 0  # given up
    assert whole.s_odo.tobytes() == s_odo.tobytes() and len(whole.s_epoch) == len(s_odo)
    with pytest.raises(ValueError, match="about a reference"):
        Recording(layout, centreline_only=True)
    whole.close()
    only.close()


def test_a_spilling_recording_has_its_read_buffers_written_beforehand(monkeypatch):
    """When a recording's chunks first spill, their writer thread writes spare arrays until the
    pool holds READ_BUFFERS of them (a fresh array costs a page fault per 4 kB; on a virtual
    machine the 10 km line's RTS lost 0.15-0.2 s to them), beyond the pool's RAM budget:
    reading the spilled chunks back then takes no new array."""
    chunks.drop_spare()
    monkeypatch.setattr(chunks, "RAM_BUDGET_BYTES", 4 * 5 * 8)  # room for one chunk array
    rows = chunks.Chunks(width=5, budget=0, rows=4, read_back=True)  # as a Recording's
    for _, _, view in rows.claim(4 * 3):  # the third chunk spills the first
        view[:] = 1.0
    rows.flush()
    assert len(chunks._SPARE[(4, 5)]) == chunks.READ_BUFFERS
    fresh = []
    empty = np.empty

    def counted(*args, **kwargs):
        fresh.append(args)
        return empty(*args, **kwargs)

    monkeypatch.setattr(chunks.np, "empty", counted)
    for i in range(rows.n_chunks - 1, -1, -1):
        assert np.all(rows.chunk(i) == 1.0)
    monkeypatch.setattr(chunks.np, "empty", empty)
    assert fresh == []
    rows.close()
    chunks.drop_spare()


@pytest.mark.parametrize("expected_chunks", [4, 12])
def test_rows_that_will_spill_keep_only_the_chunks_own_budget_in_memory(
    monkeypatch, expected_chunks
):
    """A recording's rows that fit in its budget stay in memory whole; rows that will spill
    anyway keep only RAM_BUDGET_BYTES in memory (the 100 km line at 10 Hz epochs: a peak of
    2032740 kB with a recording's 256 MB, 1786636 kB so)."""
    monkeypatch.setattr(chunks, "CHUNK_EPOCHS", 8)
    width = 4
    chunk_bytes = chunks.CHUNK_EPOCHS * width * 8
    monkeypatch.setattr(chunks, "RAM_BUDGET_BYTES", 2 * chunk_bytes)
    rows = chunks.Chunks(width, budget=4 * chunk_bytes)
    rows.expect(expected_chunks * chunks.CHUNK_EPOCHS)
    for _ in range(expected_chunks):
        rows.claim(chunks.CHUNK_EPOCHS)
    rows.flush()
    in_memory = sum(not isinstance(c, str) for c in rows._chunks)
    assert in_memory == (4 if expected_chunks == 4 else 2)
    rows.close()
    chunks.drop_spare()
