"""The alignment of two girth-weld lists by their joint lengths (the distances between
consecutive welds, m): which weld of one run is which weld of another run or of a vendor's
tally, tolerant to missed and extra welds on either side and to a scale error between the two
chainages (an odometer's). Used by the tally matching (:mod:`.tally`) and the run-to-run
movement (:mod:`.movement`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def align_sequences(
    a: Sequence[float],
    b: Sequence[float],
    *,
    scale_tolerance: float = 0.01,
    length_sigma: float = 0.1,
    max_skip: int = 4,
    match_reward: float = 10.0,
    skip_penalty: float = 2.0,
    max_residual: float = 4.0,
) -> list[tuple[int, int]]:
    """Matched index pairs (i in a, j in b), increasing in both, of two weld lists given by
    their chainages (m, increasing): the path of a dynamic programme over the joint lengths.

    A match (i, j) may follow (i', j') with up to ``max_skip`` - 1 welds skipped on either side
    (missed or extra welds); it scores ``match_reward`` minus the squared residual of the
    stretch ``(a[i] - a[i']) - k (b[j] - b[j'])`` over its sigma, less ``skip_penalty`` per
    skipped weld; residuals over ``max_residual`` sigma are not allowed. Start and end are free
    (the lists may begin and end at other welds; the chainage origins need not agree). The
    scale k: first 1 with the sigma widened by ``scale_tolerance`` of the stretch, then fitted
    to the matches (least squares, through the path) and the programme run again with
    ``length_sigma`` (m) alone. [] when fewer than two welds match.
    """
    xa = np.asarray(a, dtype=np.float64).reshape(-1)
    xb = np.asarray(b, dtype=np.float64).reshape(-1)
    if len(xa) < 2 or len(xb) < 2:
        return []
    pairs = _align(xa, xb, 1.0, length_sigma, scale_tolerance, max_skip, match_reward,
                   skip_penalty, max_residual)  # fmt: skip
    for _ in range(2):
        if len(pairs) < 3:
            break
        ia, ib = np.array(pairs).T
        k = float(np.polyfit(xb[ib], xa[ia], 1)[0])
        if not (abs(k - 1.0) <= 3.0 * scale_tolerance):
            break
        again = _align(xa, xb, k, length_sigma, 0.0, max_skip, match_reward, skip_penalty,
                       max_residual)  # fmt: skip
        if again == pairs:
            break
        pairs = again
    return pairs


def _align(
    xa: FloatArray,
    xb: FloatArray,
    scale: float,
    length_sigma: float,
    scale_tolerance: float,
    max_skip: int,
    reward: float,
    skip: float,
    max_res: float,
) -> list[tuple[int, int]]:
    """One dynamic programme of :func:`align_sequences` at a fixed scale (vectorized over j)."""
    na, nb = len(xa), len(xb)
    score = np.full((na, nb), reward)  # a path may start anywhere
    back = np.full((na, nb, 2), -1, dtype=np.int64)
    for i in range(1, na):
        for di in range(1, min(max_skip, i) + 1):
            da = xa[i] - xa[i - di]
            for dj in range(1, max_skip + 1):
                if dj >= nb:
                    break
                db = scale * (xb[dj:] - xb[:-dj])  # stretch ending at j = dj..nb-1
                sig2 = length_sigma**2 + (scale_tolerance * np.maximum(da, db)) ** 2
                r2 = (da - db) ** 2 / sig2
                cand = score[i - di, :-dj] + reward - r2 - skip * (di - 1 + dj - 1)
                cand = np.where(r2 <= max_res**2, cand, -np.inf)
                better = cand > score[i, dj:]
                if better.any():
                    js = np.flatnonzero(better) + dj
                    score[i, js] = cand[better]
                    back[i, js, 0] = i - di
                    back[i, js, 1] = js - dj
    i, j = np.unravel_index(int(np.argmax(score)), score.shape)
    path = [(int(i), int(j))]
    while back[i, j, 0] >= 0:
        i, j = back[i, j]
        path.append((int(i), int(j)))
    path.reverse()
    return path if len(path) >= 2 else []


__all__ = ["align_sequences"]
