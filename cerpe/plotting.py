"""Figure functions used by the notebooks; each returns a Figure and can save PNG + PDF.

Inputs are tidy pandas frames produced by :mod:`cerpe.pipeline.evaluate` and
:mod:`cerpe.pipeline.paper`; nothing here reads run folders or runs models.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from .errors import CerpeError

METHOD_ORDER: tuple[str, ...] = ("aliked-lightglue", "sift-ransac", "nope", "co-visnet", "cerpe-wo-em", "cerpe",
                                 "cerpe-graph")
METHOD_COLORS: dict[str, str] = {
    "aliked-lightglue": "#1f77b4", "sift-ransac": "#17becf", "nope": "#2ca02c",
    "co-visnet": "#9467bd", "cerpe-wo-em": "#ff7f0e", "cerpe": "#d62728", "cerpe-graph": "#8c564b",
}
SHORT_LABELS: dict[str, str] = {
    "aliked-lightglue": "ALIKED+LG\n(SuperGlue stand-in)", "sift-ransac": "SIFT+RANSAC",
    "nope": "NOPE", "co-visnet": "Co-VisNet", "cerpe-wo-em": "CERPE w/o EM", "cerpe": "CERPE",
    "cerpe-graph": "CERPE + graph (ours)",
}


class PlotError(CerpeError, ValueError):
    """Nothing to plot or malformed plot input."""


def _plt():
    import matplotlib

    if not os.environ.get("MPLBACKEND"):
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, stem: Path | str, dpi: int = 150) -> list[Path]:
    """Write ``<stem>.png`` and ``<stem>.pdf`` atomically (temp file + rename)."""
    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    out = []
    for ext in ("png", "pdf"):
        final = stem.with_suffix(f".{ext}")
        tmp = final.with_name(f".{final.stem}.{os.getpid()}.tmp.{ext}")
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
        os.replace(tmp, final)
        out.append(final)
    return out


def _methods_present(frames: pd.DataFrame) -> list[str]:
    present = list(dict.fromkeys(frames["method"]))
    return [m for m in METHOD_ORDER if m in present] + [m for m in present if m not in METHOD_ORDER]


# --------------------------------------------------------------------------- Fig. 4: error analysis
def error_analysis_figure(frames: pd.DataFrame, overlap_bins: Sequence[float] = (0, 0.2, 0.4, 0.6, 0.8, 1.0),
                          angle_bins: Sequence[float] = (0, 0.5, 1.0, 1.5, 2.0, 2.5, np.pi),
                          title: str = ""):
    """Rotation / GT-scale translation error by overlap-ratio and viewing-angle bins, per method.

    Args:
        frames: evaluated frames (``evaluate.frame_errors``) of one setting with
            columns ``method, success, e_rot_rad, e_pos_gt_scale_m, overlap_gt, view_angle_gt``.
    Returns:
        A 2x2 figure: rows rotation / translation error, columns overlap / angle bins.
        Failed frames are not in the boxes; the success rate per bin is printed under each box group.
    """
    import seaborn as sns

    plt = _plt()
    if frames.empty:
        raise PlotError("error_analysis_figure: no frames")
    df = frames.copy()
    df["overlap bin"] = pd.cut(df["overlap_gt"], list(overlap_bins), include_lowest=True)
    df["viewing angle bin (rad)"] = pd.cut(df["view_angle_gt"], list(angle_bins), include_lowest=True)
    methods = _methods_present(df)
    df["Method"] = df["method"].map(lambda m: SHORT_LABELS.get(m, m).replace("\n", " "))
    order_labels = [SHORT_LABELS.get(m, m).replace("\n", " ") for m in methods]
    palette = {SHORT_LABELS.get(m, m).replace("\n", " "): METHOD_COLORS.get(m, "gray") for m in methods}
    fig, axes = plt.subplots(2, 2, figsize=(13, 7.5), sharey="row")
    ok = df[df["success"]]
    for c, col in enumerate(["overlap bin", "viewing angle bin (rad)"]):
        cats = df[col].cat.categories
        for r, (y, lab) in enumerate([("e_rot_rad", "rotation error (rad)"),
                                      ("e_pos_gt_scale_m", "translation error, GT scale (m)")]):
            ax = axes[r, c]
            if ok[col].notna().any():
                sns.boxplot(data=ok, x=col, y=y, hue="Method", hue_order=order_labels, order=cats,
                            palette=palette, ax=ax, showfliers=False, linewidth=0.8)
            ax.set_ylabel(lab)
            ax.set_xlabel(col if r == 1 else "")
            ax.tick_params(axis="x", labelsize=8)
            if ax.get_legend():
                ax.get_legend().remove()
            if r == 0:
                counts = df.groupby(col, observed=False)["success"].agg(["size", "mean"])
                labels = [f"{cat}\nn={int(counts.loc[cat, 'size'])}" if cat in counts.index else str(cat)
                          for cat in cats]
                ax.set_xticks(range(len(cats)))
                ax.set_xticklabels(labels)
    handles = [plt.Rectangle((0, 0), 1, 1, color=palette[l]) for l in order_labels]
    if not df["overlap_gt"].notna().any():
        axes[0, 0].text(0.5, 0.5, "no ground-truth overlap in this setting", transform=axes[0, 0].transAxes,
                        ha="center")
    fig.suptitle(title, y=0.995)
    fig.legend(handles, order_labels, loc="upper center", ncol=len(order_labels), frameon=False,
               bbox_to_anchor=(0.5, 0.965))
    fig.tight_layout(rect=(0, 0, 1, 0.92))
    return fig


# --------------------------------------------------------------------------- qualitative
def _plane_axes(P: np.ndarray) -> tuple[int, int]:
    """The two world axes with the largest spread (a bird's-eye view without knowing 'up')."""
    spread = np.nanstd(P.reshape(-1, 3), axis=0)
    a, b = np.argsort(spread)[::-1][:2]
    return int(min(a, b)), int(max(a, b))


def qualitative_figure(traj_world: Mapping[str, np.ndarray], overlap: np.ndarray | None,
                       rel: Mapping[str, pd.DataFrame], ego: str, other: str,
                       images: Sequence[tuple[str, np.ndarray, np.ndarray]] = (), title: str = "",
                       overlap_threshold: float = 0.05,
                       metric_methods: Sequence[str] = ("cerpe", "cerpe-wo-em", "cerpe-graph")):
    """Bird's-eye view of both trajectories + collaborator position in the ego frame + image pairs.

    Args:
        traj_world: robot id -> ``[T,3]`` ground-truth camera positions (shared world frame).
        overlap: ``[T]`` ground-truth overlap ratio of the pair (or None).
        rel: method -> frame with ``step, est_tx, est_ty, est_tz, est_q*, gt_t*, gt_q*`` of
            the pair ``(ego, other)``; estimates of ``T_cj_ci``.
        images: ``(caption, image_ego, image_other)`` pairs to show in the bottom row.
    """
    from .geometry import se3_from_tq_xyzw, se3_inverse

    plt = _plt()
    n_img = len(images)
    fig = plt.figure(figsize=(13, 5.2 + (2.6 if n_img else 0)))
    gs = fig.add_gridspec(2 if n_img else 1, max(2, 2 * max(n_img, 1)),
                          height_ratios=[2.2, 1] if n_img else [1])
    ax_rel = fig.add_subplot(gs[0, : gs.ncols // 2])
    ax_bev = fig.add_subplot(gs[0, gs.ncols // 2:])
    # right: bird's-eye view of the ground truth, overlap periods marked
    P = np.stack([np.asarray(v, float) for v in traj_world.values()])
    a, b = _plane_axes(P)
    for k, (rid, p) in enumerate(traj_world.items()):
        p = np.asarray(p, float)
        ax_bev.plot(p[:, a], p[:, b], "-", color=["tab:orange", "black", "tab:blue"][k % 3],
                    label=f"{rid}" + (" (ego)" if rid == ego else ""))
        ax_bev.plot(p[0, a], p[0, b], "o", color=["tab:orange", "black", "tab:blue"][k % 3], ms=4)
        if overlap is not None and rid in (ego, other):
            ov = np.asarray(overlap) > overlap_threshold
            ax_bev.scatter(p[ov, a], p[ov, b], s=14, color="tab:green", zorder=3,
                           label="overlap" if rid == ego else None)
            ax_bev.scatter(p[~ov, a], p[~ov, b], s=14, facecolors="none", edgecolors="gray", zorder=3,
                           label="no overlap" if rid == ego else None)
    ax_bev.set_aspect("equal", "datalim")
    ax_bev.set_title("ground truth, bird's-eye view (start = dot)")
    ax_bev.set_xlabel(f"world {'xyz'[a]} (m)")
    ax_bev.set_ylabel(f"world {'xyz'[b]} (m)")
    ax_bev.legend(fontsize=8, loc="best")
    # left: collaborator's camera position in the ego camera frame (x right, z forward)
    def cam_pos(df: pd.DataFrame, prefix: str, gt_scale: bool = False) -> np.ndarray:
        from .geometry import gt_scale_translation

        cols = [f"{prefix}_{c}" for c in ("tx", "ty", "tz", "qx", "qy", "qz", "qw")]
        v = df[cols].to_numpy(float)
        if gt_scale:  # scale-free methods: translation direction with the ground-truth norm
            v[:, :3] = gt_scale_translation(v[:, :3], df[["gt_tx", "gt_ty", "gt_tz"]].to_numpy(float))
        ok = np.all(np.isfinite(v), axis=1)
        out = np.full((len(v), 3), np.nan)
        if ok.any():
            T = se3_from_tq_xyzw(v[ok, :3], v[ok, 3:])
            out[ok] = se3_inverse(T)[:, :3, 3]  # T_ci_cj translation: j's camera seen from i
        return out

    first = next(iter(rel.values()))
    g = cam_pos(first, "gt")
    ax_rel.plot(g[:, 0], g[:, 2], "k.-", lw=1.2, ms=5, label="ground truth", zorder=4)
    for m, df in rel.items():
        e = cam_pos(df, "est", gt_scale=m not in metric_methods)
        if np.isfinite(e).any():
            ax_rel.plot(e[:, 0], e[:, 2], ".-", color=METHOD_COLORS.get(m, "gray"), lw=0.9, ms=4,
                        label=SHORT_LABELS.get(m, m).replace("\n", " "), alpha=0.85)
    ax_rel.plot([0], [0], marker="^", color="tab:orange", ms=10, ls="none", label=f"ego camera {ego}")
    ax_rel.set_aspect("equal", "datalim")
    ax_rel.set_xlabel("x in ego camera (m, right)")
    ax_rel.set_ylabel("z in ego camera (m, forward)")
    ax_rel.set_title(f"position of {other} in {ego}'s camera frame\n(CERPE: predicted scale; baselines: GT scale)")
    ax_rel.legend(fontsize=7, loc="best")
    for k, (cap, im_i, im_j) in enumerate(images):
        for s, (im, who) in enumerate(((im_i, ego), (im_j, other))):
            ax = fig.add_subplot(gs[1, 2 * k + s])
            ax.imshow(im)
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"{cap}: {who}", fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


# --------------------------------------------------------------------------- communication / runtime
def communication_figure(bytes_table: pd.DataFrame, gate: pd.DataFrame, latency: pd.DataFrame,
                         paper: Mapping[str, float] | None = None, title: str = ""):
    """Bytes per robot per step, gate activations over time, per-stage latency.

    Args:
        bytes_table: columns ``scheme`` (descriptor-only / CERPE gated / [CERPE + graph gated] / always
            send images), ``bytes_per_robot_step`` (mean).
        gate: columns ``step, gate_score, gate_open, overlap_gt`` of one pair.
        latency: columns ``n_robots, stage, seconds`` (mean per team step).
        paper: the paper's own figures (descriptor KB, image KB, ms for 2/3 robots).
    """
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.3))
    ax = axes[0]
    kb = bytes_table["bytes_per_robot_step"].to_numpy(float) / 1000.0
    colours = ["tab:green", "tab:red", "tab:brown", "tab:gray"] if len(kb) == 4 else ["tab:green", "tab:red",
                                                                                      "tab:gray"][: len(kb)]
    bars = ax.bar(range(len(kb)), kb, color=colours)
    for bar_, v in zip(bars, kb):
        ax.text(bar_.get_x() + bar_.get_width() / 2, v, f"{v:.1f} KB", ha="center", va="bottom", fontsize=8)
    ax.set_xticks(range(len(kb)))
    ax.set_xticklabels(bytes_table["scheme"], fontsize=8)
    ax.set_ylabel("KB per robot per step (this run)")
    ax.set_ylim(0, 1.15 * max(np.nanmax(kb), 1e-3))
    if paper:
        ax.set_title(f"paper (other machine, VGGT/SALAD): descriptor {paper['descriptor_kb']} KB,\n"
                     f"one 640x480 JPEG {paper['image_kb']} KB", fontsize=8)
    ax = axes[1]
    if not gate.empty:
        ax.plot(gate["step"], gate["gate_score"], "-", color="tab:blue", lw=1, label="descriptor cosine")
        op = gate[gate["gate_open"].astype(bool)]
        ax.scatter(op["step"], op["gate_score"], color="tab:red", s=12, zorder=3, label="gate open: image sent")
        if "overlap_gt" in gate and gate["overlap_gt"].notna().any():
            ax.plot(gate["step"], gate["overlap_gt"], "--", color="tab:green", lw=1, label="GT overlap ratio")
        if "tau" in gate.attrs:
            ax.axhline(gate.attrs["tau"], color="k", lw=0.7, ls=":", label=f"tau = {gate.attrs['tau']:.2f}")
    ax.set_xlabel("step")
    ax.set_title(gate.attrs.get("label", "gate activations"), fontsize=9)
    ax.legend(fontsize=7)
    ax = axes[2]
    if not latency.empty:
        piv = latency.pivot_table(index="n_robots", columns="stage", values="seconds", aggfunc="mean").fillna(0.0)
        bottom = np.zeros(len(piv))
        for k, st in enumerate(piv.columns):
            ax.bar([str(i) for i in piv.index], piv[st].to_numpy() * 1000, bottom=bottom, label=st)
            bottom += piv[st].to_numpy() * 1000
        for x, v in enumerate(bottom):
            ax.text(x, v, f"{v:.0f} ms", ha="center", va="bottom", fontsize=8)
        ax.set_ylim(0, 1.15 * max(bottom.max(), 1e-3))
    ax.set_xlabel("robots in the encounter")
    ax.set_ylabel("ms per team step, all robots (this machine, CPU)")
    if paper:
        ax.set_title(f"paper (RTX 4080 laptop): {paper['ms_2']:.0f} ms (2 robots), {paper['ms_3']:.0f} ms (3)",
                     fontsize=8)
    ax.legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def gate_figure(curves: Mapping[str, tuple[np.ndarray, np.ndarray]], table: pd.DataFrame, points: pd.DataFrame,
                overlap: float = 0.2, title: str = "",
                curves_covis: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None):
    """The descriptor gate against ground-truth overlap: ROC per setting, and cosine vs overlap.

    Args:
        curves: ``{setting: (fpr, tpr)}`` with the old ordered label (dashed).
        table: rows with ``setting, roc_auc, tau, precision, recall`` (and, when
            present, ``roc_auc_ceiling``: the best AUC any symmetric score can reach,
            and ``covis_roc_auc, covis_precision, covis_recall``: the co-visibility label).
        points: rows with ``setting, gate_score, overlap_gt``.
        overlap: the overlap ratio that counts as overlapping.
        curves_covis: ``{setting: (fpr, tpr)}`` with the co-visibility label of unordered
            pairs (solid; overlap >= ``overlap`` both ways positive, < 0.05 both ways negative).
    """
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.3))
    ax = axes[0]
    colours = {}
    for s, (fpr, tpr) in (curves_covis or {}).items():
        r = table[table["setting"] == s].iloc[0]
        line, = ax.plot(fpr, tpr, lw=1.5, label=f"{s}, co-visibility label: AUC {r['covis_roc_auc']:.3f}, "
                                                 f"P {r['covis_precision']:.2f} / R {r['covis_recall']:.2f} at tau")
        colours[s] = line.get_color()
    for s, (fpr, tpr) in curves.items():
        r = table[table["setting"] == s].iloc[0]
        ceiling = r.get("roc_auc_ceiling", float("nan"))
        bound = f" (symmetric-score ceiling {ceiling:.3f})" if np.isfinite(ceiling) else ""
        ax.plot(fpr, tpr, lw=1.0, ls="--", color=colours.get(s),
                label=f"{s}, ordered label: AUC {r['roc_auc']:.3f}{bound}, P {r['precision']:.2f} / "
                      f"R {r['recall']:.2f} at tau")
    ax.plot([0, 1], [0, 1], color="0.6", lw=0.7, ls=":")
    ax.set_xlabel("false positive rate")
    ax.set_ylabel("true positive rate")
    ax.set_title(f"gate ROC: descriptor cosine vs GT co-visibility (solid: unordered pairs, overlap >= {overlap:g} "
                 f"both ways vs < 0.05 both ways; dashed: ordered pairs, overlap >= {overlap:g})", fontsize=7)
    ax.legend(fontsize=6, loc="lower right")
    ax = axes[1]
    for s, g in points.groupby("setting"):
        ax.scatter(g["overlap_gt"], g["gate_score"], s=4, alpha=0.35, label=s)
    taus = table["tau"].dropna().unique()
    for tau in taus:
        ax.axhline(tau, color="k", lw=0.7, ls=":", label=f"tau = {tau:.3f}")
    ax.axvline(overlap, color="tab:red", lw=0.7, ls="--", label=f"overlap = {overlap:g}")
    ax.set_xlabel("ground-truth overlap ratio")
    ax.set_ylabel("descriptor cosine (fp16 wire)")
    ax.legend(fontsize=7, markerscale=3)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


# --------------------------------------------------------------------------- uncertainty calibration
def calibration_figure(frames: pd.DataFrame, table: pd.DataFrame, title: str = ""):
    """Error against predicted sigma, position and rotation, per method with a covariance.

    Args:
        frames: evaluated frames of one setting (``evaluate.frame_errors``) with ``method,
            success, e_pos_m, e_rot_rad, sigma_pos_m, sigma_rot_rad``.
        table: :func:`cerpe.pipeline.evaluate.sigma_calibration` rows of the same setting.
    Returns:
        1x2 figure: each frame's error against its predicted sigma (dots), the RMS error per
        bin of predicted sigma against the bin's RMS sigma (line), and the ideal ``y = x``.
    """
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.3))
    for ax, (quantity, err, sig, unit) in zip(axes, (("position", "e_pos_m", "sigma_pos_m", "m"),
                                                     ("rotation", "e_rot_rad", "sigma_rot_rad", "rad"))):
        ok = frames[frames["success"].astype(bool)] if "success" in frames else frames
        ok = ok[np.isfinite(pd.to_numeric(ok.get(sig, pd.Series(dtype=float)), errors="coerce"))] \
            if sig in ok else ok.iloc[0:0]
        top = 0.0
        for m in _methods_present(ok) if len(ok) else []:
            f = ok[ok["method"] == m]
            c = METHOD_COLORS.get(m, "gray")
            ax.scatter(f[sig], f[err], s=5, alpha=0.3, color=c)
            t = table[(table["method"] == m) & (table["quantity"] == quantity) & (table["bin"] >= 0)]
            w = table[(table["method"] == m) & (table["quantity"] == quantity) & (table["bin"] < 0)]
            ratio = f", error/sigma {w['ratio'].iloc[0]:.2f}" if len(w) else ""
            ax.plot(t["sigma_rms"], t["error_rms"], "o-", color=c, lw=1.5,
                    label=f"{SHORT_LABELS.get(m, m)}: RMS error per sigma bin{ratio}")
            top = max(top, float(np.nanmax(np.r_[f[sig].to_numpy(float), t["error_rms"].to_numpy(float), 0])))
        if top > 0:
            ax.plot([0, top], [0, top], ":", color="0.4", lw=1, label="calibrated (error = sigma)")
            ax.legend(fontsize=7, loc="upper left")
        else:
            ax.text(0.5, 0.5, "no method with a covariance in this setting", transform=ax.transAxes, ha="center")
        ax.set_xlabel(f"predicted sigma ({unit}, RMS: sqrt of the covariance trace)")
        ax.set_ylabel(f"{quantity} error ({unit})")
        ax.set_title(quantity)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def message_loss_figure(summary: pd.DataFrame, title: str = ""):
    """Success and errors against the fraction of frames lost.

    Args:
        summary: :func:`cerpe.pipeline.message_loss.main`'s rows: ``method, loss,
            success_pct, success_after_covis_pct, e_rot_rad, e_pos_m``.
    Returns:
        1x4 figure, one line per method over loss (%).
    """
    if summary.empty:
        raise PlotError("message-loss figure: no rows")
    plt = _plt()
    fig, axes = plt.subplots(1, 4, figsize=(15, 3.6))
    panels = (("success_pct", "success (%)"), ("success_after_covis_pct", "success after co-visibility (%)"),
              ("e_rot_rad", "e_rot (rad, mean)"), ("e_pos_m", "e_pos (m, mean)"))
    for ax, (col, label) in zip(axes, panels):
        for m in [m for m in METHOD_ORDER if m in set(summary["method"])]:
            f = summary[summary["method"] == m].sort_values("loss")
            ax.plot(100 * f["loss"], f[col], "o-", color=METHOD_COLORS.get(m, "gray"), label=SHORT_LABELS.get(m, m))
        ax.set_xlabel("frames lost (%)")
        ax.set_ylabel(label)
        if col.endswith("pct"):
            ax.set_ylim(0, 105)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def pareto_figure(table: pd.DataFrame, setting: str = "all", title: str = ""):
    """Bytes per robot per step against e_rot and against e_pos, one point per scheme.

    Args:
        table: :func:`cerpe.pipeline.pareto.pareto_table` rows (``setting, scheme, label,
            bytes_per_robot_step, e_rot_rad, e_pos_m``); the rows of ``setting`` are drawn.
    Returns:
        1x2 figure (log bytes axis); a scheme without a metric position (per-frame
        baselines) is left out of the e_pos panel, which says so.
    """
    plt = _plt()
    t = table[table["setting"] == setting]
    if not len(t):
        raise PlotError(f"pareto figure: no rows for setting {setting!r}")
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.3))
    cmap = plt.get_cmap("tab10")
    for ax, (col, unit) in zip(axes, (("e_rot_rad", "rad"), ("e_pos_m", "m"))):
        left_out = []
        for k, (_, r) in enumerate(t.iterrows()):
            x, y = float(r["bytes_per_robot_step"]), float(r[col])
            if not (np.isfinite(x) and np.isfinite(y) and x > 0):
                left_out.append(str(r["scheme"]))
                continue
            ax.scatter([x / 1000], [y], s=40, color=cmap(k % 10), label=f"{r['label']}", zorder=3)
            ax.annotate(str(r["scheme"]), (x / 1000, y), textcoords="offset points", xytext=(4, 4), fontsize=7)
        ax.set_xscale("log")
        ax.set_xlabel("bytes per robot per step (KB, log)")
        ax.set_ylabel(f"mean {col[:-2].replace('_', ' ')} ({unit})")
        if left_out:
            ax.text(0.02, 0.02, "no metric value: " + ", ".join(left_out), transform=ax.transAxes, fontsize=7)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=7, loc="best")
    fig.suptitle(title or f"bytes vs accuracy ({setting})")
    fig.tight_layout()
    return fig
