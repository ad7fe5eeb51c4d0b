"""Co-visibility labels of robot pairs and the descriptor gate's quality against them.

Over the rows of ``steps.csv`` (``gate_score``, ``overlap_gt``; ``encounter, step, ego,
other``): the overlap ratio of an ordered pair ``(i, j)`` is the fraction of i's pixels
that j sees, so the two directions of a pair may differ; the co-visibility label of the
unordered pair is positive when both are at least :data:`COVIS_POSITIVE`, negative when
both are below :data:`COVIS_NEGATIVE`. ROC AUC (Mann-Whitney U), best F1 and precision /
recall at a threshold; :func:`gate_quality` puts them together for a run. Moved out of
:mod:`cerpe.pipeline.evaluate`, which re-exports every name.
"""
from __future__ import annotations

import numpy as np
import pandas as pd

GATE_OVERLAP = 0.2  # calibration: a pair "overlaps" when the GT overlap ratio is at least this
# The co-visibility label of an unordered pair: positive when the overlap ratio is at least
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


def reverse_overlap(rows: pd.DataFrame, peer_overlap: pd.DataFrame | None = None) -> np.ndarray:
    """``overlap_gt`` of each row's reverse pair (same encounter and step, ego and other swapped); NaN if absent.

    ``peer_overlap``: more rows to look the reverse pair up in (an online robot's peers' side)."""
    key = ["encounter", "step", "ego", "other"]
    if not all(c in rows.columns for c in key):
        return np.full(len(rows), np.nan)
    pool = rows[key + ["overlap_gt"]]
    if peer_overlap is not None and len(peer_overlap):
        pool = pd.concat([pool, peer_overlap[key + ["overlap_gt"]]], ignore_index=True)
    rev = pool.rename(columns={"ego": "other", "other": "ego", "overlap_gt": "_rev"})
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
    rev = reverse_overlap(steps.loc[ok])
    has_rev = np.isfinite(rev)
    out.update(symmetric_bound(s[has_rev], y[has_rev], rev[has_rev] >= overlap) if has_rev.any() else
               {"roc_auc_ceiling": float("nan"), "mixed_share": float("nan"), "roc_auc_consistent": float("nan")})
    out.update(precision_recall(s, y, out["tau"]) if tau is not None and len(s) else
               {"precision": float("nan"), "recall": float("nan")})
    out["open_rate"] = float(np.mean(s >= tau)) if tau is not None and len(s) else float("nan")
    out.update(covis_gate_quality(covisibility_pairs(steps), tau))
    return out
