"""Calibration of the descriptor's thresholds on development data (``cerpe fit thresholds``).

The gate threshold ``tau`` is set against the co-visibility label of an unordered
pair of views (:func:`cerpe.pipeline.evaluate.covisibility_label`: overlap >= 0.2
both ways positive, < 0.05 both ways negative, the rest left out). The samples of a
set (:func:`pair_samples`) are pairs of views of two different robots of one
encounter, at the same step or at any two steps (``t``, ``u`` on a stride: what the
memory-aware gate compares, and what gives a real two-fragment recording its
negatives and positives at all), labelled from depth and ground-truth poses with the
overlap ratio the datasets and the renderer use (:func:`cerpe.synth.groundtruth.overlap_ratio`).
:func:`cross_scene_negatives` adds pairs of views of two different recordings (a
different place: overlap 0 by construction), the only negatives a set whose robots
always see each other has; they are easier than a same-scene non-overlapping pair, so
a set's AUC and precision with them are upper estimates.

``tau_m`` and ``tau_k`` are low quantiles of the similarity of a robot's consecutive
frames (:func:`consecutive_similarity`).
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np
import pandas as pd

from ..pipeline.evaluate import covisibility_label, precision_recall, roc_auc

MIN_PRECISION = 0.8  # the gate's targets: recall >= 0.8 at precision >= 0.8, ROC AUC >= 0.90
MIN_RECALL = 0.8
MIN_AUC = 0.90


def describe_encounter(desc: Any, enc: Any, progress: bool = True) -> np.ndarray:
    """``[N, T, dim]`` descriptors of every robot's frames, quantised to fp16 (the wire) and unit-normed."""
    from tqdm import tqdm

    from ..protocols import View

    out = np.zeros((len(enc.robots), enc.n_steps, int(desc.dim)), np.float32)
    for i, r in enumerate(enc.robots):
        for t in tqdm(range(enc.n_steps), desc=f"describe {enc.name}/{r.robot_id}", unit="img", leave=False,
                      disable=not progress):
            d = np.asarray(desc.describe(View((r.robot_id, t), r.image(t), r.intrinsics)), np.float32)
            d = d.astype(np.float16).astype(np.float32)
            n = float(np.linalg.norm(d))
            out[i, t] = d / n if n > 0 else d
    return out


def consecutive_similarity(D: np.ndarray) -> np.ndarray:
    """Cosines of every robot's consecutive frames, ``[N * (T - 1)]``, from ``[N, T, dim]`` descriptors."""
    return np.sum(D[:, 1:] * D[:, :-1], axis=-1).ravel()


def pair_samples(enc: Any, D: np.ndarray, stride: int = 1, any_step: bool = True,
                 progress: bool = True) -> pd.DataFrame:
    """Labelled pairs of views of two robots of ``enc`` with their descriptor cosine.

    Args:
        enc: a :class:`cerpe.scene.Encounter` with depth and ground truth (any-step pairs),
            or with ``overlap`` (same-step pairs).
        D: ``[N, T, dim]`` from :func:`describe_encounter`.
        stride: steps ``t, u`` taken every ``stride``-th.
        any_step: pairs at any two steps (overlap computed from depth and poses) instead of
            the same step (``enc.overlap``).

    Returns:
        Rows ``encounter, a, b, t, u, score, o_ab, o_ba, label`` (robot indices ``a < b``,
        ``t`` for robot a, ``u`` for robot b); ``label`` NaN in the ambiguous band or where
        the overlap is unknown.
    """
    from tqdm import tqdm

    from ..synth.groundtruth import overlap_ratio

    N, T = len(enc.robots), enc.n_steps
    steps = range(0, T, max(1, int(stride)))
    rows = []
    if not any_step:
        for t in steps:
            for a in range(N):
                for b in range(a + 1, N):
                    o_ab, o_ba = ((enc.overlap[t, a, b], enc.overlap[t, b, a]) if enc.overlap is not None
                                  else (np.nan, np.nan))
                    rows.append((enc.name, a, b, t, t, float(D[a, t] @ D[b, t]), o_ab, o_ba))
    else:
        depth = [[r.depth_m(t) if r.depth is not None and r.has_gt(t) else None for t in steps] for r in enc.robots]
        for a in range(N):
            ra = enc.robots[a]
            for b in range(a + 1, N):
                rb = enc.robots[b]
                for k, t in enumerate(tqdm(steps, desc=f"co-visibility {enc.name} {ra.robot_id}-{rb.robot_id}",
                                           leave=False, disable=not progress)):
                    for m, u in enumerate(steps):
                        da, db = depth[a][k], depth[b][m]
                        if da is None or db is None:
                            o_ab = o_ba = np.nan
                        else:
                            o_ab = overlap_ratio(da, ra.intrinsics, ra.T_world_cam[t], db, rb.intrinsics,
                                                 rb.T_world_cam[u])
                            o_ba = overlap_ratio(db, rb.intrinsics, rb.T_world_cam[u], da, ra.intrinsics,
                                                 ra.T_world_cam[t])
                        rows.append((enc.name, a, b, t, u, float(D[a, t] @ D[b, u]), o_ab, o_ba))
    df = pd.DataFrame(rows, columns=["encounter", "a", "b", "t", "u", "score", "o_ab", "o_ba"])
    df["label"] = covisibility_label(df["o_ab"].to_numpy(float), df["o_ba"].to_numpy(float))
    return df


def cross_scene_negatives(D_this: np.ndarray, D_others: list[np.ndarray], stride: int = 1) -> np.ndarray:
    """Cosines of every view of this recording (``[N, T, dim]``, every ``stride``-th step) with every
    view of the other recordings: pairs of different places, label 0."""
    a = D_this[:, ::max(1, stride)].reshape(-1, D_this.shape[-1])
    out = [a @ o[:, ::max(1, stride)].reshape(-1, o.shape[-1]).T for o in D_others]
    return np.concatenate([x.ravel() for x in out]) if out else np.zeros(0)


def recall_at_precision(scores: np.ndarray, labels: np.ndarray, min_precision: float = MIN_PRECISION) -> float:
    """The highest recall of ``score >= tau`` over all ``tau`` whose precision is at least ``min_precision``
    (0 when none is; NaN without positives)."""
    s, y = np.asarray(scores, float), np.asarray(labels, bool)
    if not y.any():
        return float("nan")
    order = np.argsort(-s, kind="stable")
    s, y = s[order], y[order]
    last = np.r_[np.diff(s) != 0, True]  # thresholds at distinct scores
    tp, fp = np.cumsum(y)[last], np.cumsum(~y)[last]
    ok = tp / (tp + fp) >= min_precision
    return float(tp[ok].max() / y.sum()) if ok.any() else 0.0


def largest_tau_with_recall(sets: Mapping[str, tuple[np.ndarray, np.ndarray]], min_recall: float = MIN_RECALL,
                            decimals: int = 4) -> float:
    """The largest ``tau`` (rounded down to ``decimals``) at which ``score >= tau`` has recall
    ``>= min_recall`` on every set with positives: the smallest over sets of the score of the
    ``ceil(min_recall * P)``-th best positive."""
    taus = []
    for scores, labels in sets.values():
        pos = np.sort(np.asarray(scores, float)[np.asarray(labels, bool)])[::-1]
        if pos.size:
            k = int(np.ceil(min_recall * pos.size - 1e-9))
            taus.append(pos[max(k, 1) - 1])
    if not taus:
        raise ValueError("no set has positive pairs")
    f = 10.0 ** decimals
    return float(np.floor(min(taus) * f) / f)


def set_figures(scores: np.ndarray, labels: np.ndarray, tau: float) -> dict[str, float]:
    """A set's gate figures at ``tau``: counts, ROC AUC, precision and recall, the best recall at
    precision >= 0.8, and whether the gate's targets are met (NaN-safe: a missing class fails)."""
    s, y = np.asarray(scores, float), np.asarray(labels, bool)
    pr = precision_recall(s, y, tau)
    auc = roc_auc(s, y)
    rap = recall_at_precision(s, y)
    return {"n_positive": int(y.sum()), "n_negative": int((~y).sum()), "roc_auc": auc,
            "precision": pr["precision"], "recall": pr["recall"], "recall_at_p80": rap,
            "auc_target_met": bool(np.isfinite(auc) and auc >= MIN_AUC),
            "pr_target_met": bool(np.isfinite(rap) and rap >= MIN_RECALL)}
