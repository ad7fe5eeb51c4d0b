"""Development tools of the pose-graph back end (``cerpe-graph``): replay and noise-model samples.

Not results code: nothing here runs a model. Everything reads run folders of the cerpe
methods, whose records carry what the graph consumes (``robots.csv``: every robot's odometry
pose and degradations; ``steps.csv``: each step's direct estimate ``dir_*`` whatever its
verdict, its inliers and verdict). So the graph can be re-run on recorded passes with other
noise models in seconds (:func:`replay_run`), which is how its parameters are calibrated on
development data (``scripts/dev_graph_calibrate.py``); replaying a ``cerpe-graph`` run with
its own configuration gives its estimates back (a test checks it).

In process the channel is lossless, so robot j's broadcast pose at step t is its
``robots.csv`` pose; runs over a lossy link cannot be replayed this way.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np
import pandas as pd

from ..algorithm.graph import DirectEstimate, GraphConfig, PairGraph
from ..geometry import pose_cov_sigmas, se3_from_tq_xyzw, se3_inverse, se3_to_tq_xyzw
from .evaluate import POSE, load_run

# own-odometry failures as the agent counts them (``own_ok`` of PairGraph.step)
OWN_FAILURES = ("ego:no-estimate", "frame:blank", "ego:no-keyframe")


def _poses(df: pd.DataFrame, prefix: str) -> np.ndarray:
    v = df[[f"{prefix}_{c}" for c in POSE]].to_numpy(float)
    out = np.full((len(v), 4, 4), np.nan)
    ok = np.all(np.isfinite(v), axis=1)
    if ok.any():
        out[ok] = se3_from_tq_xyzw(v[ok, :3], v[ok, 3:])
    return out


def replay_pair(pair_steps: pd.DataFrame, ego_rows: pd.DataFrame, other_rows: pd.DataFrame,
                conf: GraphConfig) -> pd.DataFrame:
    """The graph of one ordered pair over one encounter's records: ``pair_steps`` with ``est_*``,
    ``source``, ``anchor_step``, ``sigma_pos_m``, ``sigma_rot_rad`` replaced by the replay's."""
    steps = pair_steps.sort_values("step").reset_index(drop=True)
    ego = ego_rows.set_index("step")
    other = other_rows.set_index("step")
    X_i_all, X_j_all = _poses(ego.reset_index(), "odom"), _poses(other.reset_index(), "odom")
    X_i = dict(zip(ego.index, X_i_all))
    X_j = dict(zip(other.index, X_j_all))
    failed = {t: isinstance(d, str) and any(f in d.split(";") for f in OWN_FAILURES)
              for t, d in ego["degradations"].items()}
    T_dir = _poses(steps, "dir")
    graph = PairGraph(conf)
    est = np.full((len(steps), 4, 4), np.nan)
    src, anchor, s_pos, s_rot = [], [], np.full(len(steps), np.nan), np.full(len(steps), np.nan)
    verdicts = steps["anchor_verdict"].fillna("").astype(str) if "anchor_verdict" in steps else [""] * len(steps)
    inliers = steps["direct_inliers"].fillna(-1).astype(int) if "direct_inliers" in steps else [-1] * len(steps)
    for k, t in enumerate(steps["step"].astype(int)):
        direct = (DirectEstimate(t, T_dir[k], int(inliers[k]), str(verdicts[k])) if np.all(np.isfinite(T_dir[k]))
                  else None)
        xj = X_j.get(t)
        res = graph.step(t, X_i[t], xj, t if xj is not None else -1, direct, own_ok=not failed.get(t, False))
        if res.T_cj_ci is None:
            src.append("none")
            anchor.append(-1)
            continue
        est[k] = res.T_cj_ci
        src.append("direct" if res.measured else "propagated")
        anchor.append(res.node_step)
        s_pos[k], s_rot[k] = pose_cov_sigmas(res.cov)
    out = steps.copy()
    ok = np.all(np.isfinite(est.reshape(len(est), -1)), axis=1)
    cols = np.full((len(est), 7), np.nan)
    if ok.any():
        t_, q_ = se3_to_tq_xyzw(est[ok])
        cols[ok] = np.concatenate([t_, q_], axis=1)
    for c, name in enumerate(POSE):
        out[f"est_{name}"] = cols[:, c]
    out["source"], out["anchor_step"], out["sigma_pos_m"], out["sigma_rot_rad"] = src, anchor, s_pos, s_rot
    return out


def replay_run(run_dir: Path | str, conf: GraphConfig) -> pd.DataFrame:
    """:func:`replay_pair` over every ordered pair and encounter of a cerpe-method run folder."""
    run = load_run(run_dir)
    parts = []
    for (enc, ego, other), g in run.steps.groupby(["encounter", "ego", "other"], sort=True):
        R = run.robots[run.robots["encounter"] == enc]
        parts.append(replay_pair(g, R[R["robot"] == ego], R[R["robot"] == other], conf))
    return pd.concat(parts, ignore_index=True)


def direct_samples(steps: pd.DataFrame) -> pd.DataFrame:
    """Every recorded direct estimate against ground truth: ``rot_err_rad``, ``trans_err_m`` (a right
    perturbation's, in camera i's frame, as the noise model), the translation error along the line
    between the cameras ``along_m`` (signed) and across it ``perp_m``, their distance ``dist_m``
    (ground truth), ``inliers``, ``verdict``, ``encounter``, ``step``, ``ego``, ``other``."""
    T_dir, T_gt = _poses(steps, "dir"), _poses(steps, "gt")
    ok = np.all(np.isfinite(T_dir.reshape(len(steps), -1)), axis=1) & np.all(np.isfinite(T_gt.reshape(len(steps), -1)), axis=1)
    D = se3_inverse(T_gt[ok]) @ T_dir[ok]
    from ..geometry import rotation_angle

    e = T_dir[ok][:, :3, 3] - T_gt[ok][:, :3, 3]
    dist = np.linalg.norm(T_gt[ok][:, :3, 3], axis=1)
    u = T_gt[ok][:, :3, 3] / np.maximum(dist, 1e-12)[:, None]
    along = np.sum(e * u, axis=1)
    return pd.DataFrame({
        "encounter": steps.loc[ok, "encounter"].to_numpy(), "step": steps.loc[ok, "step"].to_numpy(),
        "ego": steps.loc[ok, "ego"].to_numpy(), "other": steps.loc[ok, "other"].to_numpy(),
        "rot_err_rad": rotation_angle(D[:, :3, :3]), "trans_err_m": np.linalg.norm(D[:, :3, 3], axis=1),
        "along_m": along, "perp_m": np.linalg.norm(e - along[:, None] * u, axis=1), "dist_m": dist,
        "inliers": steps.loc[ok, "direct_inliers"].to_numpy() if "direct_inliers" in steps else -1,
        "verdict": steps.loc[ok, "anchor_verdict"].fillna("").to_numpy() if "anchor_verdict" in steps else "",
    })


def odometry_samples(robot_rows: pd.DataFrame, T_world_cam: np.ndarray, windows: tuple[int, ...] = (1, 5, 10, 20),
                     jump_rad: float = 0.0) -> Iterator[dict]:
    """Odometry increments of one robot over ``windows`` steps against ground truth ``[T,4,4]``.

    Yields ``window``, ``dist_m``, ``angle_rad`` (of the estimated increment), ``rot_err_rad``,
    ``trans_err_m`` (right perturbation, in the new camera's frame) and ``failed`` (an own-odometry
    failure within the window, or with ``jump_rad > 0`` a step turning more than that: a jump,
    which the graph models apart from the noise, ``GraphConfig.odo_jump_rad``).
    """
    from ..geometry import rotation_angle

    r = robot_rows.sort_values("step")
    X = _poses(r, "odom")
    steps = r["step"].astype(int).to_numpy()
    bad = r["degradations"].map(lambda d: isinstance(d, str) and any(f in d.split(";") for f in OWN_FAILURES)).to_numpy()
    if jump_rad > 0 and len(X) > 1:
        turn = rotation_angle((se3_inverse(X[:-1]) @ X[1:])[:, :3, :3])
        bad = bad | np.concatenate([[False], np.nan_to_num(turn, nan=0.0) > jump_rad * np.diff(steps)])
    for w in windows:
        for a in range(len(steps) - w):
            b = a + w
            Ge, Gg = se3_inverse(X[a]) @ X[b], se3_inverse(T_world_cam[steps[a]]) @ T_world_cam[steps[b]]
            if not (np.all(np.isfinite(Ge)) and np.all(np.isfinite(Gg))):
                continue
            D = se3_inverse(Gg) @ Ge
            yield {"window": w, "dist_m": float(np.linalg.norm(Ge[:3, 3])), "angle_rad": float(rotation_angle(Ge[:3, :3])),
                   "rot_err_rad": float(rotation_angle(D[:3, :3])), "trans_err_m": float(np.linalg.norm(D[:3, 3])),
                   "failed": bool(bad[a + 1: b + 1].any())}
