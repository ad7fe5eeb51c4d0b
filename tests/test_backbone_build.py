"""Plug-ins by name, depth sources, and the offline plug-ins run through cerpe.algorithm.Team end to end."""
from __future__ import annotations

import numpy as np
import pytest

from cerpe import geometry as G
from cerpe.protocols import FrameContext, View
from test_backbone_offline import K, Room, pose


def test_unknown_names_list_the_valid_ones():
    from cerpe.backbones.config import BackboneConfig
    from cerpe.backbones.depth import DepthSourceError, build_depth_source
    from cerpe.knobs import KnobError

    with pytest.raises(KnobError, match="models: 'nope' is not one of \\['offline', 'paper'\\]"):
        BackboneConfig(models="nope")
    with pytest.raises(DepthSourceError, match="sensor, mono-sim, dataset, metric3d, none"):
        build_depth_source("lidar-magic")


def test_dataset_and_none_depth():
    from cerpe.backbones.depth import DepthSourceError, build_depth_source

    img = np.zeros((4, 5, 3), np.uint8)
    d = np.array([[1.0, np.nan, -1, 2, 0]] * 4, np.float32)
    src = build_depth_source("dataset")
    out = src.depth_m(View(("r", 0), img, None), FrameContext("r", 0, None, d))
    assert out.dtype == np.float32 and out[0].tolist() == [1.0, 0, 0, 2.0, 0]
    assert src.depth_m(View(("r", 0), img, None), FrameContext("r", 0, None, None)) is None
    with pytest.raises(DepthSourceError, match="robot r step 3"):
        src.depth_m(View(("r", 3), img, None), FrameContext("r", 3, None, np.ones((2, 2))))
    assert build_depth_source("none").depth_m(View(("r", 0), img, None), FrameContext("r", 0, None, d)) is None


def test_offline_preset_through_team_with_metric_depth():
    """Two robots in a ray-cast room, exact metric depth: ego-motion drift and direct pose error."""
    from cerpe.algorithm import AlgorithmConfig, Team
    from cerpe.backbones.build import build_plugins

    room = Room(0)
    pl = build_plugins(depth="dataset")
    assert pl.descriptor.encoder is pl.backbone.encoder  # one XFeat pass per image
    team = Team(["a", "b"], pl.descriptor, pl.backbone, pl.depth, AlgorithmConfig().override({"gate.tau": 0.3, "memory.tau_m": 0.9, "memory.tau_k": 0.2, "memory.delta_k": 2}))
    traj = [lambda t: pose((0.08 * t, 0, 0.1 * t), (0, 1.0 * t, 0)),
            lambda t: pose((0.5 - 0.05 * t, 0.1, 0.2 + 0.08 * t), (0, -10 + 0.5 * t, 0))]
    X: dict[str, list[np.ndarray]] = {"a": [], "b": []}
    rot_err = []
    T = 8
    for t in range(T):
        rr = [room.render(f(t)) for f in traj]
        res = team.step([x[0] for x in rr], [FrameContext(r, t, K, x[1]) for r, x in zip("ab", rr)])
        for rec in res.robots:
            X[rec.robot].append(rec.T_odom_cam)
            assert np.all(np.isfinite(rec.T_odom_cam))
        for p in res.pairs:
            if p.source == "direct":
                gt = G.paper_T_ij(traj["ab".index(p.ego)](t), traj["ab".index(p.other)](t))
                rot_err.append(float(G.e_rot(p.T_cj_ci, gt)))
    assert len(rot_err) >= T and np.median(rot_err) < 0.05
    for r, f in zip("ab", traj):
        gt_rel = G.se3_inverse(f(0)) @ f(T - 1)
        est_rel = G.se3_inverse(X[r][0]) @ X[r][-1]
        path = sum(np.linalg.norm(f(t)[:3, 3] - f(t - 1)[:3, 3]) for t in range(1, T))
        # 320x240 renders (the 2 % target is measured at 640x480 by `cerpe bench`); the preset's 1024
        # keypoints drift 8.4 % here (2048 stayed under 8 %: the latency/accuracy trade-off of offline.keypoints)
        assert np.linalg.norm(est_rel[:3, 3] - gt_rel[:3, 3]) < 0.10 * path
        assert G.rotation_angle(est_rel[:3, :3].T @ gt_rel[:3, :3]) < np.radians(1.0)


@pytest.mark.parametrize("given", [None, "ACTIVE"])
def test_importing_cerpe_sets_a_passive_openmp_wait_policy_unless_chosen(given):
    """Idle OpenMP threads must not spin on the few cores the rest of a step needs; a
    policy the caller set is kept."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if given:
        env["OMP_WAIT_POLICY"] = given
    out = subprocess.run([sys.executable, "-c", "import os, cerpe; print(os.environ['OMP_WAIT_POLICY'])"],
                         env=env, capture_output=True, text=True, check=True).stdout.strip()
    assert out == (given or "PASSIVE")
