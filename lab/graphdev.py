"""Development tools of the pose-graph back end (``cerpe-graph``): replay and noise-model samples.

Not results code: nothing here runs a model. Everything reads run folders of the cerpe
methods, whose records carry what the graph consumes (``robots.csv``: every robot's odometry
pose and degradations; ``steps.csv``: each step's direct estimate ``dir_*`` whatever its
verdict, its inliers and verdict). So the graph can be re-run on recorded passes with other
noise models in seconds (:func:`replay_run`), which is how its parameters are calibrated on
development data (``lab/graph_calibrate.py``); replaying a ``cerpe-graph`` run with
its own noise model (:func:`run_graph_model`) gives its estimates back (a test checks it). The
noise model is a :class:`~cerpe.algorithm.graph_model.GraphModel` (the calibrated constants and
the knobs of ``backend.graph``): a study replays other values of its fields.

In process the channel is lossless, so robot j's broadcast pose at step t is its
``robots.csv`` pose; runs over a lossy link cannot be replayed this way.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Iterator

import numpy as np
import pandas as pd

from cerpe.algorithm.graph import DirectEstimate, GraphModel, PairGraph
from cerpe.algorithm.graph_model import graph_model
from cerpe.errors import CerpeError
from cerpe.geometry import pose_cov_sigmas, se3_inverse, se3_to_tq_xyzw
from cerpe.pipeline.evaluate import POSE, load_run, poses_from_columns

from .runconf import run_tree


class GraphDevError(CerpeError, ValueError):
    """Bad development-tool input: too few samples to fit, an unknown oracle (names it)."""


# own-odometry failures as the agent counts them (``own_ok`` of PairGraph.step)
OWN_FAILURES = ("ego:no-estimate", "frame:blank", "ego:no-keyframe")


def dev_sets(runs: Path) -> list[Path]:
    """The set folders under a ``cerpe dev`` runs folder that hold a ``cerpe-graph`` run, by name;
    a paper-default run (test data: never tuned on) is refused, naming the folder."""
    out = []
    for d in sorted(Path(runs).iterdir()) if Path(runs).is_dir() else []:
        if not (d / "cerpe-graph" / "run.json").is_file():
            continue
        meta = json.loads((d / "cerpe-graph" / "run.json").read_text())
        if "paper-default" in meta.get("manifest", "") or meta.get("setting", "").startswith("synthetic-"):
            raise GraphDevError(f"{d}: a paper-default run (test data); tune on development runs only")
        out.append(d)
    return out


def depth_rel_sigma(run_meta: dict) -> float | None:
    """The ``rel_sigma`` the run's depth source reports (its manifest's ``metric_depth`` and options;
    None when it reports none), as the agent hands it to the graph with each direct estimate."""
    from cerpe.backbones.depth import build_depth_source
    from cerpe.datasets.manifest import read_yaml

    raw = read_yaml(Path(run_meta["manifest"]))
    name = raw.get("metric_depth", "dataset")
    if name == "metric3d":  # not built (weights); its class says what it would report
        from cerpe.backbones.metric3d import Metric3DDepth

        return float(Metric3DDepth.rel_sigma)
    r = getattr(build_depth_source(name, raw.get("metric_depth_options") or {}), "rel_sigma", None)
    return None if r is None else float(r)


def replay_pair(pair_steps: pd.DataFrame, ego_rows: pd.DataFrame, other_rows: pd.DataFrame,
                conf: GraphModel, rel_sigma: float | None = None) -> pd.DataFrame:
    """The graph of one ordered pair over one encounter's records: ``pair_steps`` with ``est_*``,
    ``source``, ``anchor_step``, ``sigma_pos_m``, ``sigma_rot_rad`` replaced by the replay's
    (``rel_sigma``: the depth source's, :func:`depth_rel_sigma`)."""
    steps = pair_steps.sort_values("step").reset_index(drop=True)
    ego = ego_rows.set_index("step")
    other = other_rows.set_index("step")
    X_i_all, X_j_all = poses_from_columns(ego.reset_index(), "odom"), poses_from_columns(other.reset_index(), "odom")
    X_i = dict(zip(ego.index, X_i_all))
    X_j = dict(zip(other.index, X_j_all))
    failed = {t: isinstance(d, str) and any(f in d.split(";") for f in OWN_FAILURES)
              for t, d in ego["degradations"].items()}
    T_dir = poses_from_columns(steps, "dir")
    graph = PairGraph(conf, rel_sigma)
    est = np.full((len(steps), 4, 4), np.nan)
    src, anchor, s_pos, s_rot = [], [], np.full(len(steps), np.nan), np.full(len(steps), np.nan)
    verdicts = steps["anchor_verdict"].fillna("").astype(str) if "anchor_verdict" in steps else [""] * len(steps)
    inliers = steps["direct_inliers"].fillna(-1).astype(int) if "direct_inliers" in steps else [-1] * len(steps)
    stamps = (pd.to_numeric(steps["stamp_s"], errors="coerce").to_numpy(float) if "stamp_s" in steps
              else np.full(len(steps), np.nan))
    for k, t in enumerate(steps["step"].astype(int)):
        direct = (DirectEstimate(t, T_dir[k], int(inliers[k]), str(verdicts[k]), depth_rel_sigma=rel_sigma)
                  if np.all(np.isfinite(T_dir[k])) else None)
        xj = X_j.get(t)
        res = graph.step(t, X_i[t], xj, t if xj is not None else -1, direct, own_ok=not failed.get(t, False),
                         stamp_s=float(stamps[k]))
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


ORACLES: dict[str, str] = {
    "pair-scale": "each pair's direct translations divided by (1 + the median of their true relative error "
                  "along the line between the cameras): the best one distance-scale factor per pair can do",
    "no-along": "each direct estimate's translation error along the line between the cameras removed: the best "
                "a per-estimate scale correction can do",
    "exact-translation": "each direct translation replaced by the truth (rotation errors and odometry left)",
}


def oracle_steps(pair_steps: pd.DataFrame, oracle: str) -> pd.DataFrame:
    """One pair's records with its direct translations corrected from ground truth (:data:`ORACLES`):
    upper bounds of what a fix of the direct estimates' scale could give, measured by replaying."""
    if oracle not in ORACLES:
        raise GraphDevError(f"unknown oracle {oracle!r}; known: {sorted(ORACLES)}")
    cols = ["dir_tx", "dir_ty", "dir_tz"]
    t = pair_steps[cols].to_numpy(float).copy()
    tg = pair_steps[["gt_tx", "gt_ty", "gt_tz"]].to_numpy(float)
    ok = np.all(np.isfinite(t), axis=1) & np.all(np.isfinite(tg), axis=1)
    dist = np.maximum(np.linalg.norm(tg, axis=1), 1e-9)
    u = tg / dist[:, None]
    along = np.sum((t - tg) * u, axis=1)
    if oracle == "pair-scale" and ok.any():
        t[ok] /= 1.0 + float(np.median(along[ok] / dist[ok]))
    elif oracle == "no-along":
        t[ok] -= along[ok, None] * u[ok]
    elif oracle == "exact-translation":
        t[ok] = tg[ok]
    out = pair_steps.copy()
    out[cols] = t
    return out


def run_graph_model(run_dir: Path | str) -> GraphModel:
    """The noise model the pose graph of a cerpe-method run had: :data:`~cerpe.algorithm.graph_model.GRAPH_MODEL`
    with the knobs of the run's tree (``backend.graph``, ``anchors.max_unverified_steps``), as the agent builds it."""
    tree = run_tree(run_dir)
    return graph_model(tree.backend.graph, tree.anchors.max_unverified_steps)


def replay_run(run_dir: Path | str, conf: GraphModel | None = None, oracle: str | None = None) -> pd.DataFrame:
    """:func:`replay_pair` over every ordered pair and encounter of a cerpe-method run folder under noise
    model ``conf`` (None: the run's own, :func:`run_graph_model`; ``oracle``: its direct translations
    corrected first, :func:`oracle_steps`)."""
    conf = run_graph_model(run_dir) if conf is None else conf
    run = load_run(run_dir)
    rel = depth_rel_sigma(run.meta)
    parts = []
    for (enc, ego, other), g in run.steps.groupby(["encounter", "ego", "other"], sort=True):
        if oracle is not None:
            g = oracle_steps(g, oracle)
        R = run.robots[run.robots["encounter"] == enc]
        parts.append(replay_pair(g, R[R["robot"] == ego], R[R["robot"] == other], conf, rel))
    return pd.concat(parts, ignore_index=True)


def direct_samples(steps: pd.DataFrame) -> pd.DataFrame:
    """Every recorded direct estimate against ground truth: ``rot_err_rad``, ``trans_err_m`` (a right
    perturbation's, in camera i's frame, as the noise model), the translation error along the line
    between the cameras ``along_m`` (signed) and across it ``perp_m``, their distance ``dist_m``
    (ground truth), ``inliers``, ``verdict``, ``encounter``, ``step``, ``ego``, ``other``."""
    T_dir, T_gt = poses_from_columns(steps, "dir"), poses_from_columns(steps, "gt")
    ok = np.all(np.isfinite(T_dir.reshape(len(steps), -1)), axis=1) & np.all(np.isfinite(T_gt.reshape(len(steps), -1)), axis=1)
    D = se3_inverse(T_gt[ok]) @ T_dir[ok]
    from cerpe.geometry import rotation_angle

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
    which the graph models apart from the noise, ``GraphModel.odo_jump_rad``).
    """
    from cerpe.geometry import rotation_angle

    r = robot_rows.sort_values("step")
    X = poses_from_columns(r, "odom")
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


# --------------------------------------------------------------------------- direct estimates per depth kind
MAXWELL_MEDIAN = 1.5382  # median of |x| for x ~ N(0, sigma^2 I_3), in sigmas
RAYLEIGH_MEDIAN = 1.1774  # median of |x| for x ~ N(0, sigma^2 I_2), in sigmas
NORMAL_ABS_MEDIAN = 0.6745  # median of |x| for x ~ N(0, sigma^2)
MIN_REL_DIST_M = 0.5  # relative (per-metre) direct errors only from cameras at least this far apart
TRIM = 0.05  # stat "trimmed": the worst 5 % of a kind's errors left to the robust kernel
GROSS_ROT_RAD = 0.5  # direct estimates this far off are the kernel's job, not the noise model's


def _per_metre(x: np.ndarray, dist: np.ndarray, floor: float, dof: int, stat: str) -> float:
    """``b`` of a per-axis sigma ``floor + b dist`` that explains the errors ``x`` (norms over ``dof``
    axes): their median in sigmas is the Gaussian's (``stat="median"``) or their mean square is
    ``dof`` (``"rms"``); 0 when the floor alone explains them."""
    x, dist = np.abs(np.asarray(x, float)), np.asarray(dist, float)
    if len(x) == 0:
        return np.nan
    if stat == "trimmed":  # RMS of all but the worst TRIM of relative errors (the kernel's share)
        keep = x / np.maximum(dist, 1e-9) <= np.quantile(x / np.maximum(dist, 1e-9), 1.0 - TRIM)
        x, dist, stat = x[keep], dist[keep], "rms"
    k = {1: NORMAL_ABS_MEDIAN, 2: RAYLEIGH_MEDIAN}[dof]
    f = ((lambda b: float(np.median(x / (floor + b * dist))) - k) if stat == "median" else
         (lambda b: float(np.mean((x / (floor + b * dist)) ** 2)) - dof))
    if f(0.0) <= 0:
        return 0.0
    lo, hi = 0.0, 1.0
    while f(hi) > 0 and hi < 1e6:
        hi *= 10.0
    for _ in range(60):  # bisection: f decreases in b
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if f(mid) > 0 else (lo, mid)
    return 0.5 * (lo + hi)


def kind_sigmas(samples: pd.DataFrame, floor_m: float = 0.0, min_dist_m: float = MIN_REL_DIST_M,
                stat: str = "median") -> dict:
    """Per-axis sigmas of one group of direct estimates (:func:`direct_samples` rows): rotation (rad),
    and the per-metre parts across / along the line between the cameras of a sigma ``floor_m +
    b distance`` (estimates closer than ``min_dist_m`` left out of those two); ``stat``: ``median``
    (robust) or ``rms`` (what the calibration figure compares: RMS error against RMS sigma)."""
    far = samples[samples["dist_m"] >= min_dist_m]
    rot = samples["rot_err_rad"].to_numpy()
    return {"n": int(len(samples)),
            "rot": float(np.median(rot) / MAXWELL_MEDIAN if stat == "median" else
                         np.sqrt(np.mean(np.sort(rot)[: max(int(np.ceil(len(rot) * (1.0 - TRIM))), 1)] ** 2) / 3)
                         if stat == "trimmed" else np.sqrt(np.mean(rot**2) / 3)),
            "across_rel": _per_metre(far["perp_m"], far["dist_m"], floor_m, 2, stat),
            "along_rel": _per_metre(far["along_m"], far["dist_m"], floor_m, 1, stat),
            "dist_median_m": float(samples["dist_m"].median())}


def quadrature_fit(rel: np.ndarray, sigma: np.ndarray, n: np.ndarray) -> tuple[float, float]:
    """``(c, g)`` with ``sigma^2 = c^2 + (g rel)^2`` over depth kinds: non-negative least squares on the
    relative misfit, each kind weighted by its count ``n``."""
    from scipy.optimize import nnls

    w = np.asarray(n, float) / np.maximum(np.asarray(sigma, float) ** 2, 1e-12)
    r2 = np.asarray(rel, float) ** 2
    coef, _ = nnls(np.stack([w, w * r2], 1), w * np.asarray(sigma, float) ** 2)
    return float(np.sqrt(coef[0])), float(np.sqrt(coef[1]))


def fit_direct_kinds(samples: pd.DataFrame, min_kind: int = 30, stat: str = "median") -> dict:
    """The direct estimates' noise model (:func:`~cerpe.algorithm.graph_model.direct_cov`) from
    :func:`direct_samples` rows with a ``rel`` column (the depth source's relative scale sigma, NaN:
    none): floors and gains on ``rel`` fitted in quadrature over the depth kinds (one ``rel`` value
    each, at least ``min_kind`` estimates, gross ones left out), the absolute floor ``direct_trans_m``
    from cameras closer than :data:`MIN_REL_DIST_M` (else 1 mm); for estimates without a ``rel`` (no
    metric depth) ``direct_depth_rel_unknown`` as the ``rel`` that predicts their rotation and across-line
    errors (the mean of both where both gains are > 0) and ``direct_depth_along_unknown`` as the along-line
    gain on it that predicts their along-line error (:func:`~cerpe.algorithm.graph_model.along_gain`). Returns
    the :class:`~cerpe.algorithm.graph_model.GraphModel` fields, ``unknown`` (the no-depth estimates'
    observed sigmas, None without them) and ``kinds``: per kind the observed and predicted sigmas."""
    good = samples[samples["rot_err_rad"] < GROSS_ROT_RAD]
    near = good[good["dist_m"] < MIN_REL_DIST_M]
    a = max(float(np.median(near["perp_m"]) / RAYLEIGH_MEDIAN) if len(near) >= 10 else 0.0, 1e-3)
    kinds = [{"rel": float(rel), **kind_sigmas(g, a, stat=stat)} for rel, g in good[np.isfinite(good["rel"])].groupby("rel")
             if len(g) >= min_kind]
    if not kinds:
        raise GraphDevError(f"no depth kind has {min_kind} direct estimates (rot error < {GROSS_ROT_RAD} rad): "
                            "nothing to fit")
    K = pd.DataFrame(kinds)
    r, n = K["rel"].to_numpy(), K["n"].to_numpy(float)
    rot0, g_rot = quadrature_fit(r, K["rot"].to_numpy(), n)
    c, g_across = quadrature_fit(r, K["across_rel"].to_numpy(), n)
    c_along, g_along = quadrature_fit(r, K["along_rel"].to_numpy(), n)
    along_factor = float(max(c_along / max(c, 1e-9), 1.0))
    fit = {"direct_rot_rad": rot0, "direct_trans_m": a, "direct_trans_rel": c,
           "direct_along_factor": along_factor, "direct_depth_rot": g_rot, "direct_depth_across": g_across,
           "direct_depth_along": g_along}
    unknown = good[~np.isfinite(good["rel"])]
    U = kind_sigmas(unknown, a, stat=stat) if len(unknown) else None
    if U is not None:
        r_u = [np.sqrt(max(U[q] ** 2 - c0**2, 0.0)) / g for q, c0, g in (("rot", rot0, g_rot), ("across_rel", c, g_across))
               if g > 0 and np.isfinite(U[q])]
        if r_u and np.mean(r_u) > 0:
            fit["direct_depth_rel_unknown"] = float(np.mean(r_u))
            if np.isfinite(U["along_rel"]):
                fit["direct_depth_along_unknown"] = float(np.sqrt(max(U["along_rel"] ** 2 - (along_factor * c) ** 2, 0.0))
                                                          / fit["direct_depth_rel_unknown"])
    K["pred_rot"] = np.hypot(rot0, g_rot * r)
    K["pred_across_rel"] = np.hypot(c, g_across * r)
    K["pred_along_rel"] = np.hypot(along_factor * c, g_along * r)
    return {**fit, "n": int(len(samples)), "n_used": int(len(good)), "unknown": U, "kinds": K.to_dict("records")}


def along_gains_on_floors(fit: dict, conf: GraphModel) -> dict:
    """The along-line gains per depth kind that :func:`fit_direct_kinds`'s observed sigmas ask for on top of
    ``conf``'s floors (``direct_along_factor direct_trans_rel`` per metre) rather than the fitted ones:
    ``{rel: gain}`` for the kinds with ``rel > 0`` and ``"unknown"`` on ``conf.direct_depth_rel_unknown``;
    0 where the floor alone already predicts at least the observed along-line error."""
    floor = conf.direct_along_factor * conf.direct_trans_rel
    out = {float(k["rel"]): float(np.sqrt(max(k["along_rel"] ** 2 - floor**2, 0.0)) / k["rel"])
           for k in fit["kinds"] if k["rel"] > 0 and np.isfinite(k["along_rel"])}
    U = fit.get("unknown")
    if U is not None and np.isfinite(U["along_rel"]) and conf.direct_depth_rel_unknown > 0:
        out["unknown"] = float(np.sqrt(max(U["along_rel"] ** 2 - floor**2, 0.0)) / conf.direct_depth_rel_unknown)
    return out
