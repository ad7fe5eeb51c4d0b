"""The paper's metrics (Section IV) over run folders written by ``cerpe run``.

Usage: ``cerpe eval RUNDIR [RUNDIR ...] [--by encounter|setting] [--csv OUT.csv]``

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
``n_no_gt``). Run folders of one (setting, method) with different configuration
fingerprints are never aggregated together.
"""
from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import pandas as pd

from ..atomicio import AtomicIOError, atomic_write_text, read_json
from ..errors import CerpeError
from ..geometry import e_pos, e_rot_quat, gt_scale_translation, se3_from_tq_xyzw

log = logging.getLogger(__name__)

RIGHT_ROT_RAD = 0.3  # an estimate farther off in rotation is wrong (``right_pct``; issue 18's "0.3 rad wrong")

POSE = ("tx", "ty", "tz", "qx", "qy", "qz", "qw")
REQUIRED_STEP_COLS = ("encounter", "step", "stamp_s", "ego", "other", "source",
                      *(f"est_{c}" for c in POSE), *(f"gt_{c}" for c in POSE))


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


class EvalError(CerpeError, ValueError):
    """Unusable run folder (unfinished, corrupt, mixed configurations)."""


@dataclass
class Run:
    """One run folder, loaded.

    Attributes:
        path: the folder.
        meta: ``run.json``.
        steps: all encounters' ``steps.csv`` rows, concatenated.
        robots: all encounters' ``robots.csv`` rows, concatenated.
    """

    path: Path
    meta: dict
    steps: pd.DataFrame
    robots: pd.DataFrame

    @property
    def method(self) -> str:
        return self.meta["method"]

    @property
    def setting(self) -> str:
        return self.meta["setting"]

    @property
    def fingerprint(self) -> str:
        return self.meta["fingerprint"]

    @property
    def metric_scale(self) -> bool:
        return bool(self.meta.get("metric_scale", False))

    @property
    def every(self) -> int:
        return int(self.meta.get("config", {}).get("evaluation_every", 1))


def _read_csv(path: Path, required: Sequence[str] = ()) -> pd.DataFrame:
    try:
        df = pd.read_csv(path)
    except FileNotFoundError:
        raise EvalError(f"missing results file: {path}") from None
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise EvalError(f"corrupt or half-written results file {path}: {exc}") from None
    except OSError as exc:
        raise EvalError(f"cannot read results file {path}: {exc.strerror or exc}") from None
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise EvalError(f"{path}: missing columns {missing} (half-written or from another version?)")
    return df


def load_run(path: Path | str, allow_partial: bool = False) -> Run:
    """Load a run folder; every encounter of its configuration must be finished.

    Raises :class:`EvalError` naming the file for a missing/corrupt ``run.json``,
    an unfinished encounter (unless ``allow_partial``), an encounter finished
    under another fingerprint, or a corrupt CSV.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise EvalError(f"{path}: a file, not a run folder (pass the folder `cerpe run --out` wrote)")
    if not path.exists():
        raise EvalError(f"{path}: run folder not found (no {path / 'run.json'})")
    try:
        meta = read_json(path / "run.json", "run.json")
    except AtomicIOError as exc:
        raise EvalError(f"{path}: not a run folder ({exc})") from None
    for k in ("method", "setting", "fingerprint", "config"):
        if k not in meta:
            raise EvalError(f"{path / 'run.json'}: missing field {k!r}")
    if not isinstance(meta["config"], dict):
        raise EvalError(f"{path / 'run.json'}: field 'config' is not a mapping")
    steps, robots = [], []
    for enc in meta["config"].get("encounters", []):
        done = path / enc / "DONE.json"
        if not done.exists():
            if allow_partial:
                continue
            raise EvalError(f"{path}: encounter {enc!r} is not finished (no DONE.json); "
                            f"rerun `cerpe run` with the same arguments to resume")
        try:
            d = read_json(done, "DONE.json")
        except AtomicIOError as exc:
            raise EvalError(str(exc)) from None
        if d.get("fingerprint") != meta["fingerprint"]:
            raise EvalError(f"{done}: encounter finished under configuration {d.get('fingerprint')}, "
                            f"run.json says {meta['fingerprint']}: refusing to mix configurations")
        s = _read_csv(path / enc / "steps.csv", REQUIRED_STEP_COLS)
        if "n_pair_rows" in d and len(s) != int(d["n_pair_rows"]):
            raise EvalError(f"{path / enc / 'steps.csv'}: {len(s)} rows, DONE.json says {d['n_pair_rows']}")
        steps.append(s)
        robots.append(_read_csv(path / enc / "robots.csv", ("encounter", "step", "robot")))
    if not steps:
        raise EvalError(f"{path}: no finished encounter")
    sdf = pd.concat(steps, ignore_index=True)
    sdf["encounter"] = sdf["encounter"].astype(str)
    rdf = pd.concat(robots, ignore_index=True)
    rdf["encounter"] = rdf["encounter"].astype(str)
    return Run(path, meta, sdf, rdf)


GATE_OVERLAP = 0.2  # issue 4 / calibration: a pair "overlaps" when the GT overlap ratio is at least this
# The co-visibility label of an unordered pair (issue 18): positive when the overlap ratio is at least
# COVIS_POSITIVE both ways, negative when it is below COVIS_NEGATIVE both ways, left out in between
# (as place-recognition benchmarks leave out the ambiguous band).
COVIS_POSITIVE = GATE_OVERLAP
COVIS_NEGATIVE = 0.05


def roc_auc(scores: np.ndarray, labels: np.ndarray) -> float:
    """Area under the ROC curve of ``scores`` for boolean ``labels`` (Mann-Whitney U, ties averaged).

    NaN when either class is empty.
    """
    from scipy.stats import rankdata

    scores, labels = np.asarray(scores, float), np.asarray(labels, bool)
    pos, neg = int(labels.sum()), int((~labels).sum())
    if pos == 0 or neg == 0:
        return float("nan")
    r = rankdata(scores)
    return float((r[labels].sum() - pos * (pos + 1) / 2) / (pos * neg))


def roc_curve(scores: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(false positive rate, true positive rate, threshold)`` of ``score >= threshold``, thresholds descending."""
    scores, labels = np.asarray(scores, float), np.asarray(labels, bool)
    order = np.argsort(-scores, kind="stable")
    s, y = scores[order], labels[order]
    last = np.r_[np.diff(s) != 0, True]  # one point per distinct score
    tp, fp = np.cumsum(y)[last], np.cumsum(~y)[last]
    P, N = max(int(y.sum()), 1), max(int((~y).sum()), 1)
    return np.r_[0.0, fp / N], np.r_[0.0, tp / P], np.r_[np.inf, s[last]]


def best_f1(scores: np.ndarray, labels: np.ndarray) -> dict[str, float]:
    """Threshold maximising F1 of ``score >= tau`` (midpoint between neighbouring scores), with P and R at it."""
    scores, labels = np.asarray(scores, float), np.asarray(labels, bool)
    order = np.argsort(-scores)
    s, y = scores[order], labels[order]
    tp, fp = np.cumsum(y), np.cumsum(~y)
    prec, rec = tp / (tp + fp), tp / max(y.sum(), 1)
    f1 = np.where(prec + rec > 0, 2 * prec * rec / np.maximum(prec + rec, 1e-12), 0)
    k = int(np.argmax(f1))
    tau = float(0.5 * (s[k] + s[k + 1])) if k + 1 < len(s) else float(s[k])
    return {"tau": tau, "f1": float(f1[k]), **precision_recall(scores, labels, tau)}


def precision_recall(scores: np.ndarray, labels: np.ndarray, tau: float) -> dict[str, float]:
    """Precision and recall of ``score >= tau`` (NaN where undefined)."""
    pred, labels = np.asarray(scores, float) >= tau, np.asarray(labels, bool)
    tp, fp, fn = int((pred & labels).sum()), int((pred & ~labels).sum()), int((~pred & labels).sum())
    return {"precision": tp / (tp + fp) if tp + fp else float("nan"),
            "recall": tp / (tp + fn) if tp + fn else float("nan")}


def symmetric_bound(scores: np.ndarray, labels: np.ndarray, labels_rev: np.ndarray) -> dict[str, float]:
    """What a symmetric score (the gate's cosine) can reach against direction-dependent labels.

    The overlap ratio of an ordered pair ``(i, j)`` is the fraction of *i's* pixels
    that j sees, so ``(i, j)`` and ``(j, i)`` can carry different labels, while
    ``cos(d_i, d_j)`` scores both the same: one of the two is always ranked wrong.

    Args:
        scores: ``[n]`` score of each ordered pair.
        labels: ``[n]`` bool label of each ordered pair.
        labels_rev: ``[n]`` bool label of the same pair in the other direction.

    Returns:
        ``roc_auc_ceiling``: the ROC AUC of the best possible symmetric score (pairs that
        overlap both ways first, mixed pairs next, the rest last; no symmetric score can
        do better); ``mixed_share``: fraction of ordered pairs whose reverse has the
        other label; ``roc_auc_consistent``: AUC of ``scores`` on the pairs whose two
        directions agree (NaN where a class is empty).
    """
    scores = np.asarray(scores, float)
    labels, labels_rev = np.asarray(labels, bool), np.asarray(labels_rev, bool)
    both = labels.astype(float) + labels_rev.astype(float)  # 2: both ways, 1: one way, 0: neither
    consistent = labels == labels_rev
    return {"roc_auc_ceiling": roc_auc(both, labels),
            "mixed_share": float(np.mean(~consistent)) if len(labels) else float("nan"),
            "roc_auc_consistent": roc_auc(scores[consistent], labels[consistent])}


def _reverse_overlap(rows: pd.DataFrame) -> np.ndarray:
    """``overlap_gt`` of each row's reverse pair (same encounter and step, ego and other swapped); NaN if absent."""
    key = ["encounter", "step", "ego", "other"]
    if not all(c in rows.columns for c in key):
        return np.full(len(rows), np.nan)
    rev = rows[key + ["overlap_gt"]].rename(columns={"ego": "other", "other": "ego", "overlap_gt": "_rev"})
    rev = rev.drop_duplicates(key)
    return rows[key].merge(rev, on=key, how="left")["_rev"].to_numpy(float)


def covisibility_label(o_ij: np.ndarray, o_ji: np.ndarray, positive: float = COVIS_POSITIVE,
                       negative: float = COVIS_NEGATIVE) -> np.ndarray:
    """Label of the unordered pair with overlap ratios ``o_ij`` (i's pixels j sees) and ``o_ji``.

    Returns ``[n]`` float: 1 where both are ``>= positive``, 0 where both are
    ``< negative``, NaN otherwise (the ambiguous band, or an unknown overlap).
    """
    a, b = np.asarray(o_ij, float), np.asarray(o_ji, float)
    out = np.full(np.broadcast(a, b).shape, np.nan)
    out[(a >= positive) & (b >= positive)] = 1.0
    out[(a < negative) & (b < negative)] = 0.0
    return out


def covisibility_pairs(steps: pd.DataFrame) -> pd.DataFrame:
    """One row per unordered pair and step of ``steps.csv`` rows, with its co-visibility label.

    Columns ``encounter, step, a, b`` (``a < b``), ``gate_score`` (mean of the two
    directions' finite scores: the cosine is the same both ways, one may be missing),
    ``o_ab``, ``o_ba`` (the two directions' ``overlap_gt``, NaN where a row is missing)
    and ``label`` (:func:`covisibility_label`). Empty without the pair columns.
    """
    key = ["encounter", "step", "ego", "other"]
    cols = ["encounter", "step", "a", "b", "gate_score", "o_ab", "o_ba", "label"]
    if not all(c in steps.columns for c in key + ["gate_score", "overlap_gt"]) or steps.empty:
        return pd.DataFrame(columns=cols)
    df = steps[key].copy()
    ego, other = df["ego"].astype(str), df["other"].astype(str)
    df["a"], df["b"] = np.where(ego < other, ego, other), np.where(ego < other, other, ego)
    ov = pd.to_numeric(steps["overlap_gt"], errors="coerce")
    df["gate_score"] = pd.to_numeric(steps["gate_score"], errors="coerce")
    df["o_ab"] = ov.where(ego == df["a"])
    df["o_ba"] = ov.where(ego == df["b"])
    g = df.groupby(["encounter", "step", "a", "b"], sort=True).agg(
        gate_score=("gate_score", "mean"), o_ab=("o_ab", "max"), o_ba=("o_ba", "max")).reset_index()
    g["label"] = covisibility_label(g["o_ab"].to_numpy(float), g["o_ba"].to_numpy(float))
    return g[cols]


def covis_gate_quality(pairs: pd.DataFrame, tau: float | None) -> dict[str, float]:
    """The gate against the co-visibility label over :func:`covisibility_pairs` rows.

    Returns ``covis_n_pairs`` (labelled unordered pairs with a score), ``covis_n_positive``,
    ``covis_n_left_out`` (ambiguous or unknown overlap), ``covis_roc_auc``, and
    ``covis_precision``, ``covis_recall``, ``covis_open_rate`` of ``score >= tau``.
    """
    score = pairs["gate_score"].to_numpy(float)
    label = pairs["label"].to_numpy(float)
    scored = np.isfinite(score)
    ok = scored & np.isfinite(label)
    s, y = score[ok], label[ok] > 0.5
    out = {"covis_n_pairs": int(ok.sum()), "covis_n_positive": int(y.sum()),
           "covis_n_left_out": int((scored & ~np.isfinite(label)).sum()), "covis_roc_auc": roc_auc(s, y)}
    pr = (precision_recall(s, y, tau) if tau is not None and len(s) else
          {"precision": float("nan"), "recall": float("nan")})
    out.update({"covis_precision": pr["precision"], "covis_recall": pr["recall"],
                "covis_open_rate": float(np.mean(s >= tau)) if tau is not None and len(s) else float("nan")})
    return out


def gate_quality(steps: pd.DataFrame, tau: float | None, overlap: float = GATE_OVERLAP) -> dict[str, float]:
    """How well the descriptor gate predicts overlap, over all ordered pairs and steps of ``steps``.

    Uses the ``gate_score`` (cosine of the wire descriptors) and ``overlap_gt``
    columns of CERPE's ``steps.csv``; rows without either are left out.

    Returns:
        ``n_pairs``, ``n_overlapping`` (``overlap_gt >= overlap``), ``roc_auc``, ``tau``
        (the run's threshold), ``precision`` and ``recall`` at it, ``open_rate``, and
        :func:`symmetric_bound`'s ``roc_auc_ceiling``, ``mixed_share`` and
        ``roc_auc_consistent`` over the pairs whose reverse is present (NaN when
        ``encounter, step, ego, other`` are missing). These use the old, ordered label
        (``overlap_gt >= overlap`` of each direction); the ``covis_*`` fields of
        :func:`covis_gate_quality` use the symmetric co-visibility label of the
        unordered pair (both ways >= 0.2 positive, both < 0.05 negative, the rest left out).
    """
    ok = np.isfinite(pd.to_numeric(steps.get("gate_score"), errors="coerce")) & np.isfinite(
        pd.to_numeric(steps.get("overlap_gt"), errors="coerce"))
    s = steps.loc[ok, "gate_score"].to_numpy(float)
    y = steps.loc[ok, "overlap_gt"].to_numpy(float) >= overlap
    out = {"n_pairs": int(len(s)), "n_overlapping": int(y.sum()), "roc_auc": roc_auc(s, y),
           "tau": float("nan") if tau is None else float(tau)}
    rev = _reverse_overlap(steps.loc[ok])
    has_rev = np.isfinite(rev)
    out.update(symmetric_bound(s[has_rev], y[has_rev], rev[has_rev] >= overlap) if has_rev.any() else
               {"roc_auc_ceiling": float("nan"), "mixed_share": float("nan"), "roc_auc_consistent": float("nan")})
    out.update(precision_recall(s, y, out["tau"]) if tau is not None and len(s) else
               {"precision": float("nan"), "recall": float("nan")})
    out["open_rate"] = float(np.mean(s >= tau)) if tau is not None and len(s) else float("nan")
    out.update(covis_gate_quality(covisibility_pairs(steps), tau))
    return out


def first_covisible_step(steps: pd.DataFrame, overlap: float = COVIS_POSITIVE) -> np.ndarray:
    """``[n]`` per row of ``steps.csv``: the first step at which the row's pair (encounter,
    unordered robot pair) overlaps at least ``overlap`` both ways; ``inf`` where it never
    does or the overlap ground truth is missing."""
    n = len(steps)
    if n == 0 or "overlap_gt" not in steps.columns:
        return np.full(n, np.inf)
    ov = pd.to_numeric(steps["overlap_gt"], errors="coerce").to_numpy(float)
    covis = (ov >= overlap) & (_reverse_overlap(steps) >= overlap)
    ego, other = steps["ego"].astype(str), steps["other"].astype(str)
    pair = pd.DataFrame({"encounter": steps["encounter"].astype(str).to_numpy(),
                         "a": np.where(ego < other, ego, other), "b": np.where(ego < other, other, ego),
                         "t": np.where(covis, steps["step"].astype(float).to_numpy(), np.inf)})
    return pair.groupby(["encounter", "a", "b"])["t"].transform("min").to_numpy(float)


def frame_errors(steps: pd.DataFrame, metric_scale: bool, every: int = 1) -> pd.DataFrame:
    """Per-(pair, step) errors of the evaluated frames.

    Args:
        steps: rows of ``steps.csv`` (est_* and gt_* pose columns, NaN when absent).
        metric_scale: whether the method's translation is metric (else ``e_pos_m`` is NaN).
        every: evaluate every ``every``-th step (``step % every == 0``).

    Returns:
        The evaluated rows (with ground truth) plus columns ``success`` (bool),
        ``e_pos_m``, ``e_pos_gt_scale_m``, ``e_rot_rad`` (NaN where no estimate) and
        ``after_covis`` (bool: at or after the pair's first co-visible step,
        :func:`first_covisible_step`, found over all steps, evaluated or not).
    """
    first = first_covisible_step(steps)
    steps = steps.assign(after_covis=steps["step"].astype(float).to_numpy() >= first)
    df = steps[steps["step"].astype(int) % int(every) == 0].copy()
    gt = df[[f"gt_{c}" for c in POSE]].to_numpy(float)
    has_gt = np.all(np.isfinite(gt), axis=1)
    df = df[has_gt].copy()
    gt = gt[has_gt]
    est = df[[f"est_{c}" for c in POSE]].to_numpy(float)
    ok = np.all(np.isfinite(est), axis=1) & (df["source"].astype(str) != "none").to_numpy()
    df["success"] = ok
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


def summarise(frames: pd.DataFrame, by: Sequence[str]) -> pd.DataFrame:
    """Means of the errors over successful frames and the success rate, grouped by ``by``.

    ``success_after_covis_pct`` is the success rate over the frames with ``after_covis``
    (NaN where there are none), ``n_frames_after_covis`` their number; ``right_pct`` the rate
    of frames with an estimate within :data:`RIGHT_ROT_RAD` of the true rotation.
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
    return out.reset_index()


REFERENCE_METHOD = "cerpe-wo-em"  # reports only its accepted direct estimates
FRAME_KEY = ("encounter", "step", "ego", "other")


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

    Returns:
        ``(frames, runs_table)``: all evaluated frames of all runs with ``setting``
        and ``method`` columns; one row per run folder (path, fingerprint, label).
    """
    runs = [load_run(p, allow_partial=allow_partial) for p in paths]
    # the same folder twice would double-count frames
    uniq = {r.path.resolve(): r for r in runs}
    runs = list(uniq.values())
    check_consistent(runs)
    frames = []
    for r in runs:
        f = frame_errors(r.steps, r.metric_scale, r.every)
        f.insert(0, "method", r.method)
        f.insert(0, "setting", r.setting)
        f["metric_scale"] = r.metric_scale
        frames.append(f)
    table = pd.DataFrame([{"setting": r.setting, "method": r.method, "path": str(r.path),
                           "fingerprint": r.fingerprint, "label": r.meta.get("label", r.method),
                           "metric_scale": r.metric_scale} for r in runs])
    return pd.concat(frames, ignore_index=True), table


def evaluate(paths: Sequence[Path | str], by: str = "setting") -> pd.DataFrame:
    """Summary table per setting (``by='setting'``) or per encounter (``by='encounter'``)."""
    frames, _ = evaluate_runs(paths)
    keys = ["setting", "method"] + (["encounter"] if by == "encounter" else [])
    return summarise(frames, keys)


# --------------------------------------------------------------------------- CLI
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("rundirs", nargs="+", type=Path, help="run folders written by `cerpe run`")
    p.add_argument("--by", choices=("setting", "encounter"), default="setting",
                   help="aggregate per setting (Table I) or per encounter")
    p.add_argument("--csv", type=Path, default=None, help="also write the summary to this CSV file")


def main(args: argparse.Namespace) -> int:
    table = evaluate(args.rundirs, by=args.by)
    with pd.option_context("display.width", 200, "display.max_columns", 20):
        print(table.to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    print("Errors are means over frames with an estimate; frames without one count as failures "
          "(success_pct). e_pos_m is NaN for methods without metric scale. success_after_covis_pct: "
          f"success over the frames at or after the pair's first step with GT overlap >= {COVIS_POSITIVE:g} "
          f"both ways (NaN without overlap ground truth or such a step). right_pct: frames with an estimate "
          f"within {RIGHT_ROT_RAD:g} rad of the true rotation (not the paper's metric).")
    if args.csv:
        atomic_write_text(args.csv, table.to_csv(index=False))
        print(f"written: {args.csv}")
    return 0
