"""The paper's metrics (Section IV) over run folders written by ``cerpe run``
(read by :mod:`cerpe.runfolder.read`; the command line is :mod:`cerpe.pipeline.eval_cli`).

Per ordered pair ``(i, j)`` and evaluated step (every ``evaluation.every``-th
step of the manifest), with ``T_hat`` the estimate of ``T_ij = T_cj_ci`` and ``T``
the ground truth:

* ``e_pos_m = ||t_hat - t||`` (predicted, metric translation; only for methods
  that claim metric scale, NaN for the scale-free baselines),
* ``e_pos_gt_scale_m = ||t_hat ||t||/||t_hat|| - t||`` (ground-truth scale),
* ``e_rot_rad = 4 arcsin(0.5 min(||q_hat - q||, ||q_hat + q||))``,
* success: the method produced an estimate for the frame. A frame without an
  estimate (including every frame before the first anchor) is a failure: it
  counts in ``success_pct`` and is excluded from the error means.
* success after co-visibility (``success_after_covis_pct``): the success rate over
  the evaluated frames at or after the pair's first co-visible step, i.e. the first
  step whose ground-truth overlap is at least 0.2 both ways (:data:`COVIS_POSITIVE`);
  pairs that are never co-visible, and data without overlap ground truth, give none
  (NaN): before the robots have seen the same place no method can succeed directly.
* right (``right_pct``): the rate of frames with an estimate whose rotation is within
  :data:`RIGHT_ROT_RAD` (0.3 rad) of the truth. Not the paper's metric, which counts any
  pose: beside it, it tells a method that answers wrongly (a repetitive room matched one
  cubicle off) from one that says nothing.

Frames without ground truth cannot be evaluated and are left out (counted in
``n_no_gt``); a frame whose estimate in ``steps.csv`` is not finite (NaN or inf in a
pose column) is a failure, counted in ``n_nonfinite`` and warned about. Run folders
of one (setting, method) with different configuration fingerprints are never
aggregated together, except the run folders of the robots of one ``cerpe online``
team: given together they are evaluated as the team (one run, the table ``cerpe
run`` gives for the same team); a robot's folder alone is evaluated on its own
rows, co-visibility from the overlap ground truth it keeps of its peers' side.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import pandas as pd

from ..geometry import e_pos, e_rot_quat, gt_scale_translation, se3_from_tq_xyzw
from ..runfolder.layout import FRAME_KEY, POSE
from ..runfolder.read import EvalError, Run, load_run  # noqa: F401  (the metrics read run folders through them)
from ..runfolder.team import merge_teams
from .gatequality import (COVIS_NEGATIVE, COVIS_POSITIVE, GATE_OVERLAP, best_f1, covis_gate_quality,  # noqa: F401
                          covisibility_label, covisibility_pairs, gate_quality, precision_recall, reverse_overlap,
                          roc_auc, roc_curve, symmetric_bound)

log = logging.getLogger(__name__)

RIGHT_ROT_RAD = 0.3  # an estimate farther off in rotation is wrong (``right_pct``)

def poses_from_columns(df: pd.DataFrame, prefix: str) -> np.ndarray:
    """``[N,4,4]`` poses of the ``<prefix>_tx .. <prefix>_qw`` columns of a results table (``est``, ``gt``,
    ``dir``, ``odom``); NaN matrices where a row has none."""
    v = df[[f"{prefix}_{c}" for c in POSE]].to_numpy(float)
    out = np.full((len(v), 4, 4), np.nan)
    ok = np.all(np.isfinite(v), axis=1)
    if ok.any():
        out[ok] = se3_from_tq_xyzw(v[ok, :3], v[ok, 3:])
    return out


SUMMARY_COLS = ("e_pos_m", "e_pos_gt_scale_m", "e_rot_rad", "success_pct", "n_frames", "success_after_covis_pct",
                "right_pct")


def first_covisible_step(steps: pd.DataFrame, overlap: float = COVIS_POSITIVE,
                         peer_overlap: pd.DataFrame | None = None) -> np.ndarray:
    """``[n]`` per row of ``steps.csv``: the first step at which the row's pair (encounter,
    unordered robot pair) overlaps at least ``overlap`` both ways; ``inf`` where it never
    does or the overlap ground truth is missing (``peer_overlap``: see :func:`~cerpe.pipeline.gatequality.reverse_overlap`)."""
    n = len(steps)
    if n == 0 or "overlap_gt" not in steps.columns:
        return np.full(n, np.inf)
    ov = pd.to_numeric(steps["overlap_gt"], errors="coerce").to_numpy(float)
    covis = (ov >= overlap) & (reverse_overlap(steps, peer_overlap) >= overlap)
    ego, other = steps["ego"].astype(str), steps["other"].astype(str)
    pair = pd.DataFrame({"encounter": steps["encounter"].astype(str).to_numpy(),
                         "a": np.where(ego < other, ego, other), "b": np.where(ego < other, other, ego),
                         "t": np.where(covis, steps["step"].astype(float).to_numpy(), np.inf)})
    return pair.groupby(["encounter", "a", "b"])["t"].transform("min").to_numpy(float)


def frame_errors(steps: pd.DataFrame, metric_scale: bool, every: int = 1,
                 peer_overlap: pd.DataFrame | None = None) -> pd.DataFrame:
    """Per-(pair, step) errors of the evaluated frames.

    Args:
        steps: rows of ``steps.csv`` (est_* and gt_* pose columns, NaN when absent).
        metric_scale: whether the method's translation is metric (else ``e_pos_m`` is NaN).
        every: evaluate every ``every``-th step (``step % every == 0``).
        peer_overlap: an online robot's peers' ``overlap_gt`` rows (see :func:`first_covisible_step`).

    Returns:
        The evaluated rows (with ground truth) plus columns ``success`` (bool),
        ``e_pos_m``, ``e_pos_gt_scale_m``, ``e_rot_rad`` (NaN where no estimate),
        ``nonfinite`` (bool: an estimate with NaN or inf in it, a failure) and
        ``after_covis`` (bool: at or after the pair's first co-visible step,
        :func:`first_covisible_step`, found over all steps, evaluated or not).
    """
    first = first_covisible_step(steps, peer_overlap=peer_overlap)
    steps = steps.assign(after_covis=steps["step"].astype(float).to_numpy() >= first)
    df = steps[steps["step"].astype(int) % int(every) == 0].copy()
    gt = df[[f"gt_{c}" for c in POSE]].to_numpy(float)
    has_gt = np.all(np.isfinite(gt), axis=1)
    df = df[has_gt].copy()
    gt = gt[has_gt]
    est = df[[f"est_{c}" for c in POSE]].to_numpy(float)
    claimed = (df["source"].astype(str) != "none").to_numpy()
    finite = np.all(np.isfinite(est), axis=1)
    ok = finite & claimed
    df["success"] = ok
    df["nonfinite"] = ~finite & (claimed | ~np.all(np.isnan(est), axis=1))
    n = len(df)
    e_p = np.full(n, np.nan)
    e_pg = np.full(n, np.nan)
    e_r = np.full(n, np.nan)
    if ok.any():
        t_hat, q_hat = est[ok, :3], est[ok, 3:]
        t, q = gt[ok, :3], gt[ok, 3:]
        if metric_scale:
            e_p[ok] = e_pos(t_hat, t)
        e_pg[ok] = e_pos(gt_scale_translation(t_hat, t), t)
        e_r[ok] = e_rot_quat(q_hat, q)
    df["e_pos_m"] = e_p
    df["e_pos_gt_scale_m"] = e_pg
    df["e_rot_rad"] = e_r
    return df


def no_gt_frames(steps: pd.DataFrame, every: int = 1) -> pd.DataFrame:
    """The rows of ``steps.csv`` at evaluated steps without (finite) ground truth: left out of every metric."""
    df = steps[steps["step"].astype(int) % int(every) == 0]
    return df[~np.all(np.isfinite(df[[f"gt_{c}" for c in POSE]].to_numpy(float)), axis=1)]


def summarise(frames: pd.DataFrame, by: Sequence[str], no_gt: pd.DataFrame | None = None) -> pd.DataFrame:
    """Means of the errors over successful frames and the success rate, grouped by ``by``.

    ``success_after_covis_pct`` is the success rate over the frames with ``after_covis``
    (NaN where there are none), ``n_frames_after_covis`` their number; ``right_pct`` the rate
    of frames with an estimate within :data:`RIGHT_ROT_RAD` of the true rotation; ``n_nonfinite``
    the frames whose estimate is not finite (failures). With ``no_gt`` (:func:`no_gt_frames` rows
    with the ``by`` columns), ``n_no_gt`` counts the frames left out for want of ground truth.
    """
    after = frames["after_covis"].astype(bool) if "after_covis" in frames else pd.Series(False, frames.index)
    right = frames["success"].astype(bool) & (frames["e_rot_rad"].to_numpy(float) <= RIGHT_ROT_RAD)
    frames = frames.assign(_succ_ac=frames["success"].astype(float).where(after), _after=after,
                           _right=right.astype(float))
    g = frames.groupby(list(by), sort=True, dropna=False)
    out = pd.DataFrame({
        "e_pos_m": g["e_pos_m"].mean(),
        "e_pos_gt_scale_m": g["e_pos_gt_scale_m"].mean(),
        "e_rot_rad": g["e_rot_rad"].mean(),
        "e_rot_median_rad": g["e_rot_rad"].median(),
        "success_pct": 100.0 * g["success"].mean(),
        "n_frames": g["success"].size(),
        "n_success": g["success"].sum(),
        "success_after_covis_pct": 100.0 * g["_succ_ac"].mean(),
        "n_frames_after_covis": g["_after"].sum(),
        "right_pct": 100.0 * g["_right"].mean(),
    })
    if "nonfinite" in frames:
        out["n_nonfinite"] = g["nonfinite"].sum().astype(int)
    out = out.reset_index()
    if no_gt is not None:
        n = no_gt.groupby(list(by), sort=True, dropna=False).size().rename("n_no_gt").reset_index()
        out = out.merge(n, on=list(by), how="left")
        out["n_no_gt"] = out["n_no_gt"].fillna(0).astype(int)
    return out


REFERENCE_METHOD = "cerpe-wo-em"  # reports only its accepted direct estimates


def e_pos_on_reference_frames(frames: pd.DataFrame, reference: str = REFERENCE_METHOD,
                              by: Sequence[str] = ("setting",), column: str = "e_pos_m") -> pd.DataFrame:
    """Each method's mean ``column`` (``e_pos_m``; ``e_pos_gt_scale_m`` for methods without a predicted
    scale) over the frames where ``reference`` reports one.

    Methods that report on different frames are not compared by their own means: CERPE w/o EM
    answers only where a direct estimate was accepted, CERPE and the graph also between them
    (propagated, farther from the last measurement). Over the reference's frames (those the
    method reports too) they are compared like for like.

    Args:
        frames: :func:`frame_errors` rows with ``method`` and the ``by`` columns.

    Returns:
        ``by + [method, e_pos_on_ref_frames_m, n_ref_frames]``: NaN and 0 where the group has
        no ``reference`` run or the method reports on none of its frames.
    """
    by, key = list(by), [*by, *FRAME_KEY]
    cols = [*by, "method", "e_pos_on_ref_frames_m", "n_ref_frames"]
    if frames.empty or not set(key) <= set(frames.columns):
        return pd.DataFrame(columns=cols)
    pos = frames[np.isfinite(pd.to_numeric(frames[column], errors="coerce"))]
    ref = pos.loc[pos["method"] == reference, key].drop_duplicates()
    on = pos.merge(ref, on=key, how="inner")
    g = on.groupby([*by, "method"], sort=True)[column]
    out = pd.DataFrame({"e_pos_on_ref_frames_m": g.mean(), "n_ref_frames": g.size()}).reset_index()
    every = frames[[*by, "method"]].drop_duplicates()
    out = every.merge(out, on=[*by, "method"], how="left")
    out["n_ref_frames"] = out["n_ref_frames"].fillna(0).astype(int)
    return out[cols].reset_index(drop=True)


SIGMA_COLS = {"position": ("e_pos_m", "sigma_pos_m"), "rotation": ("e_rot_rad", "sigma_rot_rad")}


def sigma_calibration(frames: pd.DataFrame, n_bins: int = 6, by: Sequence[str] = ("setting", "method")) -> pd.DataFrame:
    """Error against predicted sigma (calibration) over frames with an estimate and a covariance.

    ``sigma_pos_m`` / ``sigma_rot_rad`` (``steps.csv``, methods with a covariance: ``cerpe-graph``)
    are predicted RMS errors (``sqrt`` of the covariance block's trace), so a calibrated method
    has, per bin of predicted sigma, an RMS error equal to the bin's RMS sigma (ratio 1).

    Returns one row per group of ``by``, quantity (``position``, ``rotation``) and bin (quantiles
    of the predicted sigma): ``n``, ``sigma_rms`` (RMS predicted sigma), ``error_rms`` (RMS error),
    ``ratio`` (``error_rms / sigma_rms``) and ``within_2sigma_pct`` (errors within twice their own
    sigma); a ``bin`` of -1 is the whole group. Empty without such frames.
    """
    cols = [*by, "quantity", "bin", "n", "sigma_rms", "error_rms", "ratio", "within_2sigma_pct"]
    rows = []
    for quantity, (err, sig) in SIGMA_COLS.items():
        if err not in frames or sig not in frames:
            continue
        f = frames[frames["success"].astype(bool)].copy()
        f = f[np.isfinite(pd.to_numeric(f[err], errors="coerce")) & np.isfinite(pd.to_numeric(f[sig], errors="coerce"))]
        for key, g in f.groupby(list(by), sort=True):
            e, sg = g[err].to_numpy(float), g[sig].to_numpy(float)
            edges = np.unique(np.quantile(sg, np.linspace(0, 1, max(int(n_bins), 1) + 1)))
            idx = np.clip(np.searchsorted(edges, sg, side="right") - 1, 0, max(len(edges) - 2, 0))
            for b in [-1, *range(max(len(edges) - 1, 1))]:
                m = np.ones(len(e), bool) if b < 0 else idx == b
                if not m.any():
                    continue
                s_rms, e_rms = float(np.sqrt(np.mean(sg[m] ** 2))), float(np.sqrt(np.mean(e[m] ** 2)))
                rows.append({**dict(zip(by, key if isinstance(key, tuple) else (key,))), "quantity": quantity,
                             "bin": b, "n": int(m.sum()), "sigma_rms": s_rms, "error_rms": e_rms,
                             "ratio": e_rms / s_rms if s_rms > 0 else float("nan"),
                             "within_2sigma_pct": 100.0 * float(np.mean(e[m] <= 2 * sg[m]))})
    return pd.DataFrame(rows, columns=cols)


def check_consistent(runs: Iterable[Run]) -> None:
    """Refuse runs that must not share a table.

    * one (setting, method) with two fingerprints (two configurations), or twice;
    * the cerpe methods run under different profiles or seeds, or settings
      evaluated with different ``evaluation.every`` across methods.
    """
    runs = list(runs)
    seen: dict[tuple[str, str], Run] = {}
    for r in runs:
        key = (r.setting, r.method)
        if key in seen and seen[key].fingerprint != r.fingerprint:
            raise EvalError(f"refusing to aggregate mixed configurations for setting {r.setting!r}, method "
                            f"{r.method!r}: {seen[key].path} ({seen[key].fingerprint}) vs {r.path} "
                            f"({r.fingerprint})")
        if key in seen:  # same configuration twice (a copied folder) would count every frame twice
            raise EvalError(f"setting {r.setting!r}, method {r.method!r} given twice ({seen[key].path} and "
                            f"{r.path}); pass one run folder per setting and method")
        seen[key] = r
    models = {r.meta.get("config", {}).get("method_config", {}).get("tree", {}).get("backbone", {}).get("models")
              for r in runs if r.metric_scale}
    if len(models) > 1:
        raise EvalError(f"refusing to aggregate CERPE runs of different models {sorted(map(str, models))}")
    seeds = {int(r.meta.get("seed", 0)) for r in runs}
    if len(seeds) > 1:
        raise EvalError(f"refusing to aggregate runs with different seeds {sorted(seeds)}")
    every: dict[str, set[int]] = {}
    for r in runs:
        every.setdefault(r.setting, set()).add(r.every)
    bad = {s: v for s, v in every.items() if len(v) > 1}
    if bad:
        raise EvalError(f"refusing to aggregate: evaluation.every differs within settings {bad}")


def evaluate_runs(paths: Sequence[Path | str], allow_partial: bool = False) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Load run folders, check they may be aggregated, compute frame errors.

    The folders of one ``cerpe online`` team are evaluated as one run (:mod:`cerpe.runfolder.team`).

    Returns:
        ``(frames, runs_table)``: all evaluated frames of all runs with ``setting``
        and ``method`` columns; one row per run (path(s), fingerprint, label).
    """
    frames, _, table = _evaluate_runs(paths, allow_partial)
    return frames, table


def _evaluate_runs(paths: Sequence[Path | str], allow_partial: bool = False
                   ) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """:func:`evaluate_runs`, and the rows left out for want of ground truth (:func:`no_gt_frames`)."""
    runs = [load_run(p, allow_partial=allow_partial) for p in paths]
    # the same folder twice would double-count frames
    uniq = {r.path.resolve(): r for r in runs}
    runs = merge_teams(list(uniq.values()))
    check_consistent(runs)
    frames, no_gt = [], []
    for r in runs:
        f, n = frame_errors(r.steps, r.metric_scale, r.every, r.peer_overlap), no_gt_frames(r.steps, r.every).copy()
        for df in (f, n):
            df.insert(0, "method", r.method)
            df.insert(0, "setting", r.setting)
        f["metric_scale"] = r.metric_scale
        frames.append(f)
        no_gt.append(n)
    table = pd.DataFrame([{"setting": r.setting, "method": r.method, "path": ", ".join(map(str, r.paths or (r.path,))),
                           "fingerprint": r.fingerprint, "label": r.meta.get("label", r.method),
                           "metric_scale": r.metric_scale} for r in runs])
    return pd.concat(frames, ignore_index=True), pd.concat(no_gt, ignore_index=True), table


def evaluate(paths: Sequence[Path | str], by: str = "setting") -> pd.DataFrame:
    """Summary table per setting (``by='setting'``) or per encounter (``by='encounter'``), with ``n_no_gt``;
    logs a warning for frames with a non-finite estimate and for frames left out without ground truth."""
    frames, no_gt, _ = _evaluate_runs(paths)
    keys = ["setting", "method"] + (["encounter"] if by == "encounter" else [])
    table = summarise(frames, keys, no_gt)
    for row in table[(table["n_nonfinite"] > 0) | (table["n_no_gt"] > 0)].itertuples():
        where = "/".join(str(getattr(row, k)) for k in keys)
        if row.n_nonfinite:
            log.warning("%s: %d frame(s) with a non-finite estimate (NaN or inf) in steps.csv, counted as "
                        "failures (n_nonfinite)", where, row.n_nonfinite)
        if row.n_no_gt:
            log.warning("%s: %d frame(s) without ground truth, left out of every metric (n_no_gt)", where, row.n_no_gt)
    return table
