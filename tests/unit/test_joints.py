"""The alignment of two weld lists by their joint lengths (products/joints.py): missed and
extra welds, a scale error, a stretch inside a longer list."""

import numpy as np
import pytest
from pipe_nav_core.products.joints import align_sequences


def _sequences(rng, n=300, scale=1.007, miss=0.05, extra=10):
    joints = 12.0 + rng.uniform(-0.4, 0.4, n)
    truth = np.cumsum(np.r_[12.0, joints])
    a_keep = np.flatnonzero(rng.random(len(truth)) > miss)
    b_keep = np.flatnonzero(rng.random(len(truth)) > miss)
    a = truth[a_keep] + rng.normal(0, 0.02, len(a_keep))
    b = scale * truth[b_keep] + 3.0 + rng.normal(0, 0.03, len(b_keep))
    at = rng.choice(len(truth) - 1, extra, replace=False)  # a false weld inside a joint
    fake = scale * (truth[at] + rng.uniform(0.25, 0.75, extra) * joints[at]) + 3.0
    b_all = np.r_[b, fake]
    lab = np.r_[b_keep, -np.ones(extra, dtype=int)]
    order = np.argsort(b_all)
    return a, a_keep, b_all[order], lab[order]


@pytest.mark.parametrize("scale", [0.99, 0.999, 1.0, 1.004, 1.01])
def test_alignment_with_missed_and_extra_welds_and_a_scale_error(scale):
    rng = np.random.default_rng(int(scale * 1e4))
    a, a_lab, b, b_lab = _sequences(rng, scale=scale)
    pairs = align_sequences(a, b, scale_tolerance=0.01)
    possible = len(set(a_lab) & set(b_lab[b_lab >= 0]))
    right = sum(a_lab[i] == b_lab[j] for i, j in pairs)
    assert right == len(pairs)  # no wrong match
    assert right >= 0.97 * possible
    ii, jj = np.array(pairs).T
    assert np.all(np.diff(ii) > 0) and np.all(np.diff(jj) > 0)


def test_alignment_of_a_stretch_inside_a_longer_list():
    rng = np.random.default_rng(11)
    a, a_lab, b, b_lab = _sequences(rng, n=200, miss=0.0, extra=0, scale=1.0)
    inner = slice(50, 120)
    pairs = align_sequences(a[inner] - 500.0, b)
    assert len(pairs) >= 65
    assert all(a_lab[inner][i] == b_lab[j] for i, j in pairs)


def test_alignment_of_too_short_lists_is_empty():
    assert align_sequences([], [1.0, 2.0]) == []
    assert align_sequences([5.0], [1.0, 13.0]) == []
