"""Ground truth of in-memory encounters: depth consistency across views, overlap, determinism;
simulated depth sources."""
from __future__ import annotations

import numpy as np
import pytest

from cerpe.depthsim import MonoDepthSim, SensorDepthSim
from cerpe.geometry import paper_T_ij
from cerpe.protocols import FrameContext, MetricDepthSource, View
from cerpe.synth import render_encounter
from cerpe.synth.groundtruth import backproject, overlap_ratio, reproject_check
from cerpe.synth.worlds import plan_encounter

CONF = {"n_frames": 6, "fps": 2.0, "size": (160, 120)}


@pytest.fixture(scope="module")
def indoor():
    return render_encounter("indoor-team", seed=4, index=0, conf=CONF)


@pytest.fixture(scope="module")
def cad():
    return render_encounter("cad-intersection", seed=4, index=1, conf={**CONF, "n_robots": 2})


@pytest.mark.parametrize("which", ["indoor", "cad"])
def test_reprojected_depth_agrees_with_the_other_view(which, request):
    enc = request.getfixturevalue(which)
    checked = 0
    for t in range(enc.n_steps):
        for i, j in enc.ordered_pairs():
            a, b = enc.robots[i], enc.robots[j]
            pts, _ = backproject(a.depth_m(t), a.intrinsics, stride=2)
            _, z, d = reproject_check(pts, paper_T_ij(a.T_world_cam[t], b.T_world_cam[t]), b.depth_m(t), b.intrinsics,
                                      bilinear=True)
            # same surface in j: exclude occlusions with a generous 10 % gate, then the median must be < 1 %
            same = (d > 0) & (np.abs(z - d) < 0.1 * d)
            if same.sum() < 200:
                continue
            rel = np.abs(z[same] - d[same]) / d[same]
            assert np.median(rel) < 0.01, (which, t, i, j, np.median(rel))
            checked += 1
    assert checked >= 3


def test_overlap_of_a_view_with_itself_is_one_and_shapes(indoor):
    r = indoor.robots[0]
    d = r.depth_m(2)
    assert overlap_ratio(d, r.intrinsics, r.T_world_cam[2], d, r.intrinsics, r.T_world_cam[2], 1) == pytest.approx(1.0)
    assert indoor.overlap.shape == (6, 3, 3) and np.all((indoor.overlap >= 0) & (indoor.overlap <= 1))
    assert indoor.meta["viewing_angle_rad"].shape == (6, 3, 3)
    # an image of the room has no sky
    assert (d > 0).mean() > 0.99


def test_plans_are_deterministic_in_the_seed():
    c = {**CONF, "n_robots": 2}
    a = plan_encounter("cad-intersection", 7, 2, c)
    b = plan_encounter("cad-intersection", 7, 2, c)
    other = plan_encounter("cad-intersection", 8, 2, c)
    np.testing.assert_array_equal(a.T_world_cam, b.T_world_cam)
    assert not np.allclose(a.T_world_cam, other.T_world_cam)


def test_cad_trajectories_are_smooth_and_at_vehicle_speed():
    plan = plan_encounter("cad-intersection", 0, 3, {"n_frames": 30, "fps": 10.0, "size": (64, 48), "n_robots": 2})
    for k in range(2):
        p = plan.T_world_cam[k][:, :3, 3]
        v = np.linalg.norm(np.diff(p, axis=0), axis=1) * 10.0
        assert np.all((v > 2.5) & (v < 11.0))
        assert np.all(np.abs(p[:, 2] - 1.5) < 1e-9)
        acc = np.abs(np.diff(v)) * 10.0
        assert acc.max() < 3.0  # no jumps


def _ctx(enc, k=0, t=1, seed=0):
    r = enc.robots[k]
    return View((r.robot_id, t), r.image(t), r.intrinsics), FrameContext(r.robot_id, t, r.intrinsics, r.depth_m(t), seed)


def test_sensor_sim_is_deterministic_and_respects_its_model(indoor):
    sim = SensorDepthSim(min_m=0.3, max_m=4.0)
    assert isinstance(sim, MetricDepthSource) and sim.name == "sensor"
    view, fr = _ctx(indoor)
    a, b = sim.depth_m(view, fr), sim.depth_m(view, fr)
    np.testing.assert_array_equal(a, b)
    view2, fr2 = _ctx(indoor, t=2)
    assert not np.array_equal(sim.depth_m(view2, fr2), a)
    z = fr.sensor_depth_m
    assert np.all((a == 0) | ((a > 0.25) & (a < 4.1)))
    assert 0.5 < (a > 0).sum() / ((z >= 0.3) & (z <= 4.0)).sum() < 0.99  # dropouts and edges, not everything
    ok = a > 0
    rel = np.abs(a[ok] - z[ok]) / z[ok]
    assert np.median(rel) < 0.01
    # noise grows with z^2: residual std far vs near
    near, far = ok & (z < 1.5), ok & (z > 2.5)
    if near.sum() > 50 and far.sum() > 50:
        assert np.std(a[far] - z[far]) > np.std(a[near] - z[near])
    assert sim.depth_m(view, FrameContext("r0", 1, None, None)) is None


def test_mono_sim_has_a_per_frame_scale_bias(indoor):
    sim = MonoDepthSim(seed=3)
    assert isinstance(sim, MetricDepthSource) and sim.name == "mono-sim"
    ratios = []
    for t in range(indoor.n_steps):
        view, fr = _ctx(indoor, t=t)
        d = sim.depth_m(view, fr)
        np.testing.assert_array_equal(d, sim.depth_m(view, fr))
        z = fr.sensor_depth_m
        ok = z > 0
        assert np.all(d[~ok] == 0) and np.all(d[ok] > 0)
        ratios.append(np.median(d[ok] / z[ok]))
    ratios = np.array(ratios)
    assert np.all((ratios > 0.6) & (ratios < 1.6))
    assert ratios.std() > 0.01  # the bias changes from frame to frame
    other = MonoDepthSim(seed=4).depth_m(*_ctx(indoor, t=0))
    assert not np.allclose(other, MonoDepthSim(seed=3).depth_m(*_ctx(indoor, t=0)))


@pytest.mark.parametrize("seed", range(20))
def test_depth_edges_are_pixels_next_to_a_jump_or_a_hole(seed):
    """:func:`depth_edges` against its definition, pixel by pixel: a 4-neighbour whose depth jumps by
    more than ``rel_jump`` of the nearer one, or only one of the two has depth; then dilated."""
    import cv2

    from cerpe.depthsim import depth_edges

    rng = np.random.default_rng(seed)
    H, W = rng.integers(1, 24, 2)
    H, W = (1 if seed % 5 == 3 else H), (1 if seed % 5 == 4 else W)  # one-pixel-wide maps: pairs one way only
    z = (rng.uniform(0.5, 3.0, (H, W)) * (rng.random((H, W)) < 0.8)).astype(np.float32)
    if seed % 2:
        z = np.round(z, 1)  # plateaus: equal neighbours are never an edge
    want = np.zeros((H, W), bool)
    for i in range(H):
        for j in range(W):
            for a, b in ((i - 1, j), (i + 1, j), (i, j - 1), (i, j + 1)):
                if 0 <= a < H and 0 <= b < W:
                    c, n = z[i, j], z[a, b]
                    want[i, j] |= bool(abs(n - c) > 0.05 * max(min(n, c), 1e-3)) or (n > 0) != (c > 0)
    assert np.array_equal(depth_edges(z, dilate_px=0), want)
    grown = cv2.dilate(want.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert np.array_equal(depth_edges(z, dilate_px=2), grown)


@pytest.mark.parametrize("seed", range(12))
def test_upper_quantile_is_numpys(seed):
    """:func:`upper_quantile` partitions only the values above a sampled bound: the same float as
    ``np.quantile`` (linear), bit for bit, with ties, plateaus, small arrays and low quantiles too."""
    from cerpe.depthsim import upper_quantile

    rng = np.random.default_rng(seed)
    n = int(rng.choice([7, 4095, 4096, 30_000, 307_200]))
    v = rng.standard_normal(n).astype(np.float32)
    if seed % 3 == 1:
        v = np.round(v, 1)  # many ties
    if seed % 3 == 2:
        v[: n // 2] = v.max()  # half the values equal to the largest
    for q in (0.97, 0.999, 0.9, 0.5, 0.0, 1.0):
        assert upper_quantile(v.reshape(-1, 1) if seed % 2 else v, q) == float(np.quantile(v, q))
