"""The pose graph without metric depth: rotations fused, translations the switch's (never worse than them)."""
from __future__ import annotations

import numpy as np
import pytest

from cerpe.algorithm import AlgorithmConfig, Team
from cerpe.algorithm import relative as relative_mod
from cerpe.algorithm.graph_model import GRAPH_MODEL, UNSCALED_TRANS_SIGMA, DirectEstimate, direct_cov, odometry_cov
from cerpe.geometry import e_rot, make_se3, so3_exp
from gt_backbone import GTBackbone, OverlapDescriptor, make_world


class NoDepthDouble:
    """A depth source that never has metric depth (RGB only): every pass has a unit of its own."""

    name, metric, rel_sigma = "none", False, None

    def depth_m(self, view, frame):
        return None


def _run(world, backend: str) -> list:
    # the gate always open: a direct estimate at every step (through passes of random units)
    cfg = AlgorithmConfig().override({"scale.min_pixels": 20, "gate.tau": -1.0, "backend.kind": backend})
    team = Team(world.robot_ids, OverlapDescriptor(world), GTBackbone(world, seed=1, rot_noise_rad=0.01,
                                                                      trans_noise=0.02), NoDepthDouble(), cfg)
    return list(team.run_encounter(world.to_encounter()))


def _errors(world, results) -> dict[tuple[int, str], tuple[float, float]]:
    """(step, ego) -> (translation direction error deg, rotation error rad) of every estimate."""
    out = {}
    for r in results:
        for p in r.pairs:
            if p.T_cj_ci is None:
                continue
            G = world.gt_T_cj_ci(r.step, world.index(p.ego), world.index(p.other))
            a, b = p.T_cj_ci[:3, 3], G[:3, 3]
            deg = np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1.0, 1.0)))
            out[(r.step, p.ego)] = (float(deg), float(e_rot(p.T_cj_ci, G)))
    return out


def _old_graph(monkeypatch) -> None:
    """The graph as it was: translations fused as if metric, and reported as the graph's."""
    gm = relative_mod.graph_model
    monkeypatch.setattr(relative_mod, "graph_model", lambda conf, steps, metric=True: gm(conf, steps, True))
    monkeypatch.setattr(relative_mod.Relative, "_unscaled", staticmethod(
        lambda res, switch: ("direct" if res.measured else "propagated", res.T_cj_ci, switch[2], res.node_step,
                             res.cov) if res.T_cj_ci is not None else ("none", None, switch[2], -1, None)))


@pytest.mark.parametrize("seed", [0, 1])
def test_rgb_only_graph_keeps_the_switchs_translations_where_the_old_one_reversed_them(seed, monkeypatch):
    world = make_world(2, 30, seed=seed)
    switch, graph = _errors(world, _run(world, "switch")), _errors(world, _run(world, "graph"))
    assert switch.keys() == graph.keys() and len(switch) == 2 * 30  # the same frames
    assert max(d for d, _ in switch.values()) < 10.0  # the switch is right
    assert all(graph[k][0] == pytest.approx(switch[k][0], abs=1e-9) for k in switch)  # its directions, kept
    # rotations fused by the graph: no worse than the switch's
    assert np.mean([r for _, r in graph.values()]) <= 1.02 * np.mean([r for _, r in switch.values()])
    _old_graph(monkeypatch)
    old = _errors(world, _run(world, "graph"))
    assert max(d for d, _ in old.values()) > 90.0  # translations reversed: the units of the passes mixed


def test_unscaled_model_gives_translations_no_information():
    unscaled = GRAPH_MODEL.__class__(metric=False)
    T = make_se3(so3_exp(np.array([0.0, 0.1, 0.0])), np.array([0.5, 0.0, 2.0]))
    cov, ref = direct_cov(unscaled, DirectEstimate(3, T)), direct_cov(GRAPH_MODEL, DirectEstimate(3, T))
    np.testing.assert_allclose(cov[:3, :3], ref[:3, :3])  # rotation as before
    np.testing.assert_allclose(cov[3:, 3:], np.eye(3) * UNSCALED_TRANS_SIGMA**2)
    assert not cov[:3, 3:].any() and not cov[3:, :3].any()
    odo = odometry_cov(unscaled, T, 1)
    np.testing.assert_allclose(odo[3:, 3:], np.eye(3) * UNSCALED_TRANS_SIGMA**2)
    np.testing.assert_allclose(odo[:3, :3], odometry_cov(GRAPH_MODEL, T, 1)[:3, :3])


def test_rgb_only_graph_reports_rotation_covariance_and_unknown_translation():
    world = make_world(2, 20, seed=2)
    rows = [p.as_row() for r in _run(world, "graph") for p in r.pairs if p.T_cj_ci is not None]
    assert rows and all(np.isfinite(r["sigma_rot_rad"]) and np.isnan(r["sigma_pos_m"]) for r in rows if r["source"] != "none")


def test_a_rotation_only_covariance_keeps_its_rotation_block_in_the_cov_file():
    from cerpe.geometry import pose_cov_in_parent
    from cerpe.tum import format_tum_cov, parse_tum_cov

    T = make_se3(so3_exp(np.array([0.1, -0.2, 0.3])), np.array([1.0, 2.0, 3.0]))
    C = np.diag([1e-4, 2e-4, 3e-4, 1.0, 1.0, 1.0])
    partial = C.copy()
    partial[3:, :], partial[:, 3:] = np.nan, np.nan
    _, (full, half) = parse_tum_cov(format_tum_cov(np.array([0.0, 1.0]), np.stack([T, T]), np.stack([C, partial])))
    np.testing.assert_allclose(half[3:, 3:], full[3:, 3:], rtol=1e-6)  # ROS order: rotation last
    np.testing.assert_allclose(full, pose_cov_in_parent(T, C), rtol=1e-6)
    assert np.isnan(half[:3, :]).all() and np.isnan(half[:, :3]).all()
