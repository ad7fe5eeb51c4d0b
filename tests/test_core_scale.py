"""Scale recovery: known factor through invalid pixels and outliers, resizing, skips, errors."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cerpe.scale import ScaleError, recover_scale, resize_nearest


def _corrupt(rng: np.random.Generator, D: np.ndarray, s: float, invalid: float = 0.3, outliers: float = 0.05):
    """Metric = s * D, then `invalid` of the pixels made unusable in one of the four
    ways (metric 0, metric NaN, backbone 0, confidence 0) and `outliers` of the
    pixels given a wrong metric depth."""
    Dstar = s * D
    D = D.copy()
    conf = np.ones_like(D)
    n = D.size
    perm = rng.permutation(n)
    n_inv, n_out = int(invalid * n), int(outliers * n)
    bad = perm[:n_inv]
    for k, how in enumerate(np.array_split(bad, 4)):
        if k == 0:
            Dstar.flat[how] = 0.0
        elif k == 1:
            Dstar.flat[how] = np.nan
        elif k == 2:
            D.flat[how] = 0.0
        else:
            conf.flat[how] = 0.0
    out = perm[n_inv:n_inv + n_out]
    Dstar.flat[out] = rng.uniform(0.01, 1000.0, out.size)
    return Dstar, D, conf


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(0.01, 100.0), st.integers(1, 5))
def test_recovers_known_factor_with_invalid_pixels_and_outliers(seed, s, K):
    rng = np.random.default_rng(seed)
    metric, backbone, conf = [], [], []
    for _ in range(K):
        h, w = rng.integers(12, 40, 2)
        D = rng.uniform(0.5, 30.0, (h, w))
        a, b, c = _corrupt(rng, D, s)
        metric.append(a), backbone.append(b), conf.append(c)
    est = recover_scale(metric, backbone, conf, min_pixels=20)
    assert est.ok and est.n_used == K and not est.skipped
    assert est.scale == pytest.approx(s, rel=1e-9)
    np.testing.assert_allclose(est.medians, s, rtol=1e-9)


def test_is_mean_of_per_keyframe_medians():
    D = np.full((10, 10), 2.0)
    est = recover_scale([D * 1.0, D * 3.0], [D, D], min_pixels=1)
    assert est.scale == pytest.approx(2.0)  # (1 + 3) / 2, not a pooled median
    np.testing.assert_allclose(est.medians, [1.0, 3.0])


def test_metric_map_of_other_resolution_is_resampled_nearest():
    rng = np.random.default_rng(0)
    D = rng.uniform(1, 10, (12, 16))
    Dstar_hi = np.kron(2.5 * D, np.ones((3, 3)))          # 36 x 48: each backbone pixel a 3x3 block
    Dstar_hi[1::3, 1::3] = 2.5 * D                          # block centres exact (they are anyway)
    Dstar_hi[0::3, 0::3] = 0.0                              # corners unknown: nearest must not pick them
    est = recover_scale([Dstar_hi], [D], min_pixels=10)
    assert est.scale == pytest.approx(2.5, rel=1e-12)
    assert est.n_valid_pixels[0] == D.size
    lo = resize_nearest(np.arange(16.0).reshape(4, 4), (2, 2))
    np.testing.assert_array_equal(lo, [[5, 7], [13, 15]])
    up = resize_nearest(np.array([[1.0, 2.0]]), (2, 4))
    np.testing.assert_array_equal(up, [[1, 1, 2, 2], [1, 1, 2, 2]])


def test_skips_and_reports_unusable_keyframes():
    D = np.ones((10, 10))
    sparse = np.zeros((10, 10))
    sparse[0, :5] = 4.0
    est = recover_scale([2 * D, sparse, None, 2 * D], [D, D, D, None], min_pixels=10)
    assert est.scale == pytest.approx(2.0)
    assert est.n_used == 1
    assert est.skipped == [(1, "too-few-pixels"), (2, "no-metric-depth"), (3, "no-backbone-depth")]
    assert np.isnan(est.medians[1:]).all()
    assert est.n_valid_pixels[1] == 5


def test_no_valid_keyframe_gives_nan_with_reason_never_division_by_zero():
    z = np.zeros((8, 8))
    with np.errstate(all="raise"):
        est = recover_scale([z, np.ones((8, 8))], [np.ones((8, 8)), z], min_pixels=1)
    assert np.isnan(est.scale) and not est.ok and est.n_used == 0
    assert "too-few-pixels" in est.reason
    empty = recover_scale([], [])
    assert np.isnan(empty.scale) and empty.reason == "no keyframes"


def test_non_finite_and_negative_backbone_depth_is_invalid():
    D = np.ones((10, 10))
    D[0] = -1.0
    D[1] = np.inf
    est = recover_scale([3 * np.ones((10, 10))], [D], min_pixels=1)
    assert est.scale == pytest.approx(3.0)
    assert est.n_valid_pixels[0] == 80


@pytest.mark.parametrize("metric, backbone, conf, field", [
    ([np.ones(5)], [np.ones((5, 5))], None, r"metric_depths_m\[0\]"),
    ([np.ones((5, 5)), np.ones((5, 5, 1))], [np.ones((5, 5))] * 2, None, r"metric_depths_m\[1\]"),
    ([np.ones((5, 5))], [np.ones((1, 5, 5))], None, r"backbone_depths\[0\]"),
    ([np.ones((5, 5))], [np.ones((5, 5))], [np.ones((4, 5))], r"confidences\[0\]"),
    ([np.ones((5, 5))], [np.ones((5, 5))] * 2, None, "metric depths for 2"),
    ([np.ones((5, 5))], [np.ones((5, 5))], [], "confidence maps"),
])
def test_malformed_input_raises_naming_argument(metric, backbone, conf, field):
    with pytest.raises(ScaleError, match=field):
        recover_scale(metric, backbone, conf, min_pixels=1)
