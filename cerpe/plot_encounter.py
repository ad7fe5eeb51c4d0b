"""One encounter at a glance: where each method puts the other robot, and its errors step by step.

:func:`encounter_figure` draws what ``cerpe demo`` writes and what the walkthrough notebook ends
with. Inputs are evaluated frames (:func:`cerpe.pipeline.evaluate.frame_errors` rows) and the
ground-truth camera poses; nothing here reads run folders or runs models.
"""
from __future__ import annotations

from typing import Mapping

import numpy as np
import pandas as pd

from .geometry import gt_scale_translation, se3_from_tq_xyzw, se3_inverse
from .pipeline.evaluate import POSE, RIGHT_ROT_RAD
from .plotting import METHOD_COLORS, METHOD_ORDER, SHORT_LABELS, PlotError, _plane_axes, _plt

FLOOR = 1e-4  # errors below this are drawn at it (log axes)
ROBOT_COLORS = ("black", "tab:gray")


def _label(method: str) -> str:
    return SHORT_LABELS.get(method, method).replace("\n", " ")


def other_in_world(rows: pd.DataFrame, T_world_ci: np.ndarray, gt_scale: bool) -> np.ndarray:
    """``[N,3]`` world position of camera j where each row's estimate puts it, seen from camera i's
    true pose: ``T_world_ci @ inv(T_cj_ci)`` (NaN where a row has no estimate).

    Args:
        rows: frames of one ordered pair ``(i, j)`` with ``step``, ``est_*`` and ``gt_*`` columns.
        T_world_ci: ``[T,4,4]`` camera i's true camera-to-world poses, indexed by step.
        gt_scale: put the estimated translation at the true distance (methods without metric scale).
    """
    est = rows[[f"est_{c}" for c in POSE]].to_numpy(float)
    out = np.full((len(rows), 3), np.nan)
    ok = np.all(np.isfinite(est), axis=1)
    if not ok.any():
        return out
    t = est[ok, :3]
    if gt_scale:
        t = gt_scale_translation(t, rows[["gt_tx", "gt_ty", "gt_tz"]].to_numpy(float)[ok])
    T_ci_cj = se3_inverse(se3_from_tq_xyzw(t, est[ok, 3:]))
    steps = rows["step"].to_numpy(int)[ok]
    out[ok] = (T_world_ci[steps] @ T_ci_cj)[:, :3, 3]
    return out


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``(first, last)`` index of each run of True in ``mask``."""
    runs, start = [], None
    for k, v in enumerate(list(mask) + [False]):
        if v and start is None:
            start = k
        elif not v and start is not None:
            runs.append((start, k - 1))
            start = None
    return runs


def _plain_log_ticks(ax) -> None:
    """Log y ticks labelled as plain numbers: 1-2-5 steps over a range under two decades, decades beyond."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    lo, hi = ax.get_ylim()
    ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0) if np.log10(hi / lo) < 2 else (1.0,)))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.yaxis.set_minor_formatter(NullFormatter())


def _series(f: pd.DataFrame) -> list[tuple[str, pd.DataFrame, bool, str, str]]:
    """Per method in table order: ``(method, its rows by step, metric scale, colour, legend name)``."""
    present = list(dict.fromkeys(f["method"]))
    out = []
    for m in [m for m in METHOD_ORDER if m in present] + [m for m in present if m not in METHOD_ORDER]:
        rows = f[f["method"] == m].sort_values("step")
        metric = bool(rows["metric_scale"].iloc[0]) if "metric_scale" in rows else True
        out.append((m, rows, metric, METHOD_COLORS.get(m, "tab:purple"),
                    _label(m) + ("" if metric else " (true distance)")))
    return out


def _draw_paths(ax, P: np.ndarray, names: tuple[str, str], a: int, b: int) -> None:
    """The true paths ``P [2,T,3]`` of ego and other on plane axes ``a``, ``b``, their starts labelled."""
    for k, rid in enumerate(names):
        ax.plot(P[k, :, a], P[k, :, b], ".-", color=ROBOT_COLORS[k], lw=1.5, ms=4, zorder=2,
                label=f"{rid} true path, a dot per step" + ("" if k else " (ego)"))
        ax.plot(P[k, 0, a], P[k, 0, b], "o", color=ROBOT_COLORS[k], ms=8, zorder=5)
        ax.annotate(f"{rid} start", (P[k, 0, a], P[k, 0, b]), textcoords="offset points", xytext=(-8, 0),
                    ha="right", va="center", fontsize=8, color=ROBOT_COLORS[k], zorder=5,
                    bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.8})


def _draw_errors(ax_rot, ax_pos, series: list, overlap: pd.Series | None, overlap_threshold: float) -> None:
    """Rotation and position error per step; overlap steps shaded, a cross where a method has no estimate."""
    if overlap is not None:
        steps = overlap.index.to_numpy(int)
        for k, (s0, s1) in enumerate(_runs(overlap.to_numpy(float) > overlap_threshold)):
            for ax in (ax_rot, ax_pos):
                ax.axvspan(steps[s0] - 0.5, steps[s1] + 0.5, color="tab:green", alpha=0.12, lw=0,
                           label="views overlap (truth)" if (k == 0 and ax is ax_rot) else None)
    for n, (_, rows, metric, color, name) in enumerate(series):
        step = rows["step"].to_numpy(int)
        src = rows["source"].astype(str).to_numpy()
        e_pos = rows["e_pos_m" if metric else "e_pos_gt_scale_m"].to_numpy(float)
        for ax, err in ((ax_rot, rows["e_rot_rad"].to_numpy(float)), (ax_pos, e_pos)):
            y = np.maximum(err, FLOOR)
            ax.plot(step, y, "-", color=color, lw=1, alpha=0.7, label=name)
            for kind, face in (("direct", color), ("propagated", "white")):
                sel = (src == kind) & np.isfinite(err)
                ax.scatter(step[sel], y[sel], s=18, marker="o" if metric else "s", facecolors=face,
                           edgecolors=color, linewidths=1, zorder=3)
            none = src == "none"
            ax.scatter(step[none], np.full(none.sum(), 0.04 + 0.06 * n), marker="x", color=color, s=22, zorder=3,
                       transform=ax.get_xaxis_transform())  # axes height: one row of crosses per method
    ax_rot.axhline(RIGHT_ROT_RAD, color="tab:red", ls="--", lw=0.8, label=f"right: within {RIGHT_ROT_RAD:g} rad")
    strip = 0.04 + 0.06 * len(series)  # the bottom of each panel, left to the crosses
    for ax, what in ((ax_rot, "rotation error (rad)"), (ax_pos, "position error (m)")):
        ax.set_yscale("log")
        lo, hi = ax.get_ylim()
        ax.set_ylim(lo / (hi / lo) ** (strip / (1 - strip)), hi)
        _plain_log_ticks(ax)
        ax.set_ylabel(what)
        ax.grid(alpha=0.3, which="both")
    steps = np.concatenate([rows["step"].to_numpy(int) for _, rows, _, _, _ in series])
    ax_rot.set_xlim(steps.min() - 0.7, steps.max() + 0.7)  # the crosses do not widen the axis
    ax_rot.tick_params(labelbottom=False)
    ax_pos.set_xlabel("step (x at the bottom: no estimate; open marker: propagated)")
    ax_rot.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, 1.32), ncol=2, frameon=False)


def encounter_figure(frames: pd.DataFrame, T_world_cam: Mapping[str, np.ndarray], ego: str, other: str,
                     title: str = "", overlap_threshold: float = 0.05):
    """Bird's-eye view of one encounter with each method's estimate of ``other``, beside its errors per step.

    Args:
        frames: evaluated frames with ``method, step, ego, other, source, est_*, gt_*, e_rot_rad,
            e_pos_m, e_pos_gt_scale_m``; optional ``metric_scale`` (False: the method's translation
            has no scale, drawn and scored at the true distance) and ``overlap_gt``.
        T_world_cam: robot id -> ``[T,4,4]`` true camera-to-world poses in one world frame, by step.
        ego, other: the ordered pair drawn (``ego``'s estimates of ``other``).
        overlap_threshold: steps whose true overlap exceeds it are shaded in the error panels.

    Left: both true trajectories (dot = start) and, per method, where the estimate puts ``other``'s
    camera when composed with ``ego``'s true pose; filled markers are direct estimates, open ones
    propagated. Right: rotation and position error per step on log axes; the dashed line is the
    "right" threshold (0.3 rad), a cross at the bottom a step without an estimate.
    """
    f = frames[(frames["ego"].astype(str) == ego) & (frames["other"].astype(str) == other)]
    if f.empty:
        raise PlotError(f"encounter figure: no frames of the pair {ego} -> {other}")
    if ego not in T_world_cam or other not in T_world_cam:
        raise PlotError(f"encounter figure: no ground-truth poses of {ego!r} or {other!r}")
    series = _series(f)
    plt = _plt()
    fig = plt.figure(figsize=(13, 6.2))
    gs = fig.add_gridspec(2, 2, width_ratios=[1.15, 1], hspace=0.08, wspace=0.22)
    ax_bev = fig.add_subplot(gs[:, 0])
    ax_rot = fig.add_subplot(gs[0, 1])
    ax_pos = fig.add_subplot(gs[1, 1], sharex=ax_rot)
    # left: true trajectories and where each estimate puts `other`, joined to the truth at its step
    P = np.stack([np.asarray(T_world_cam[r], float)[:, :3, 3] for r in (ego, other)])
    a, b = _plane_axes(P)
    _draw_paths(ax_bev, P, (ego, other), a, b)
    for _, rows, metric, color, name in series:
        pos = other_in_world(rows, np.asarray(T_world_cam[ego], float), gt_scale=not metric)
        truth = P[1, rows["step"].to_numpy(int)]
        for k in np.flatnonzero(np.all(np.isfinite(pos), axis=1)):
            ax_bev.plot([truth[k, a], pos[k, a]], [truth[k, b], pos[k, b]], "-", color=color, lw=0.6, alpha=0.35,
                        zorder=1)
        src = rows["source"].astype(str).to_numpy()
        for kind, face in (("direct", color), ("propagated", "none")):
            sel = src == kind
            if sel.any():
                ax_bev.scatter(pos[sel, a], pos[sel, b], s=26, marker="o" if metric else "s", facecolors=face,
                               edgecolors=color, linewidths=1.2, zorder=3, label=f"{name}: {kind}")
    ax_bev.set_aspect("equal", "datalim")
    ax_bev.set_xlabel(f"world {'xyz'[a]} (m)")
    ax_bev.set_ylabel(f"world {'xyz'[b]} (m)")
    ax_bev.set_title(f"where {ego} puts {other} (bird's-eye; thin lines: estimate to truth)", fontsize=10)
    ax_bev.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=2, frameon=False)
    ax_bev.grid(alpha=0.3)
    overlap = f.groupby("step")["overlap_gt"].first().sort_index() if "overlap_gt" in f else None
    _draw_errors(ax_rot, ax_pos, series, overlap, overlap_threshold)
    if title:
        fig.suptitle(title, y=1.02)
    return fig
