"""Replay robots of a dev encounter alone and print their per-step ego-motion against ground truth.

Each robot runs in a team of its own (its ego-motion never reads a collaborator's view in a
depth pass). Per robot: the sum and max of the per-step translation errors
(``||t_est - t_gt||`` of ``(X^{t-1})^-1 X^t``, metres); with ``--trace`` per step the estimated
and true step lengths, the error, the keyframe count and the backbone's vote (the votes of the
prior view and of each chained view per motion hypothesis, and the prior view's moving pixels).

    python -m lab.ego_replay build/dev/manifests/dev-synthetic-cad-s2002.yaml cad-l2-s2002-e02 r1 --trace
    python -m lab.ego_replay build/dev/manifests/dev-synthetic-cad-s2002.yaml   # every robot, first 15 steps
"""
from __future__ import annotations

import argparse

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("manifest")
    ap.add_argument("encounter", nargs="?", default="all", help="an encounter's name, or all (default)")
    ap.add_argument("robot", nargs="?", default="all", help="a robot id, or all (default)")
    ap.add_argument("--steps", type=int, default=15)
    ap.add_argument("--trace", action="store_true", help="print the vote of every pass")
    a = ap.parse_args()
    from cerpe.pipeline.cerpe_method import cerpe_plugins_and_config
    from cerpe.pipeline.setting import load_manifest_setting
    from cerpe.backbones.offline import vote

    setting = load_manifest_setting(a.manifest)
    plugins, cfg, _ = cerpe_plugins_and_config("cerpe", getattr(setting, "metric_depth", None),
                                               getattr(setting, "metric_depth_options", None))
    if a.trace:
        import cerpe.backbones.offline.reconstruction as rc

        def traced(p, d, T_0_d):
            per = [vote.motion_votes(p, d, T_0_d).tolist()]
            per += [vote.motion_votes(p, k, [T @ T_d_k for T in T_0_d]).tolist() for k, T_d_k in vote.chained_views(p, d)]
            mv = p.moving(d)
            ts = [f"{np.linalg.norm(T[:3, 3]):.3f}" for T in T_0_d]
            print(f"    vote d={d} |t|={ts} votes={per} moving(d)={None if mv is None else int(mv.sum())}")
            return vote.total_votes(p, d, T_0_d)

        rc.total_votes = traced
    total = []
    for enc in setting.encounters:
        if a.encounter not in ("all", enc.name):
            continue
        for rob in enc.robots:
            if a.robot in ("all", rob.robot_id):
                errs = replay(enc, rob, plugins, cfg, a.steps, a.trace)
                total += errs
                print(f"{enc.name} {rob.robot_id}: sum err {sum(errs):.3f} max {max(errs):.3f} "
                      f"steps > 0.1 m: {sum(e > 0.1 for e in errs)}", flush=True)
    print(f"all: sum err {sum(total):.3f} steps > 0.1 m: {sum(e > 0.1 for e in total)} of {len(total)}")


def replay(enc, rob, plugins, cfg, steps: int, trace: bool) -> list[float]:
    """Per-step translation errors of robot ``rob`` of ``enc`` replayed alone (first ``steps`` steps)."""
    from cerpe.algorithm.team import Team
    from cerpe.protocols import FrameContext

    team = Team([rob.robot_id], plugins.descriptor, plugins.backbone, plugins.depth, cfg)
    team.reset()
    X_prev = None
    errs = []
    for t in range(min(steps, enc.n_steps)):
        if trace:
            print(f"step {t}")
        res = team.step([rob.image(t)], [FrameContext(rob.robot_id, t, rob.intrinsics, rob.depth_m(t), 0)],
                        [float(rob.stamps_s[t])])
        X = res.robots[0].T_odom_cam
        if X_prev is not None:
            est = np.linalg.inv(X_prev) @ X
            gt = np.linalg.inv(rob.T_world_cam[t - 1]) @ rob.T_world_cam[t]
            e = float(np.linalg.norm(est[:3, 3] - gt[:3, 3]))
            errs.append(e)
            if trace:
                print(f"t={t:2d} est {np.linalg.norm(est[:3, 3]):.3f} gt {np.linalg.norm(gt[:3, 3]):.3f} "
                      f"err {e:.3f} kf={res.robots[0].n_keyframes}")
        X_prev = X
    return errs


if __name__ == "__main__":
    main()
