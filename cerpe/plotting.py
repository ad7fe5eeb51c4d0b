"""Figure functions used by the notebooks; each returns a Figure and can save PNG + PDF.

Inputs are tidy pandas frames produced by :mod:`cerpe.pipeline.evaluate` and
:mod:`cerpe.pipeline.paper`; nothing here reads run folders or runs models. Legends sit outside the
data; a figure that shows one example says by which rule it was chosen (:func:`gate_example_setting`).
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
    "aliked-lightglue": "ALIKED+LG (SuperGlue stand-in)", "sift-ransac": "SIFT+RANSAC",
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


def _legend_below(ax, ncol: int = 2, fontsize: float = 7, **kw):
    """A legend under ``ax`` (outside the data, so it never covers a point or a label)."""
    return ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=ncol, fontsize=fontsize,
                     frameon=False, **kw)


def _plain_log_ticks(axis) -> None:
    """Plain numbers on a log axis (``0.01``, ``2``, not ``10^-2``, ``2x10^0``); the minor ticks at 2 and
    5 are labelled only when the axis spans under two decades (else they would collide)."""
    from matplotlib.ticker import FuncFormatter, NullFormatter

    lo, hi = sorted(axis.get_view_interval())
    axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    few = lo > 0 and np.log10(hi / lo) < 2
    axis.set_minor_formatter(FuncFormatter(lambda v, _: f"{v:g}" if v > 0 and round(v / 10 ** np.floor(
        np.log10(v) + 1e-9)) in (2, 5) else "") if few else NullFormatter())


# --------------------------------------------------------------------------- Fig. 4: error analysis
def error_analysis_figure(frames: pd.DataFrame, overlap_bins: Sequence[float] = (0, 0.2, 0.4, 0.6, 0.8, 1.0),
                          angle_bins: Sequence[float] = (0, 0.5, 1.0, 1.5, 2.0, 2.5, np.pi),
                          title: str = ""):
    """Rotation / GT-scale translation error and success rate by overlap-ratio and viewing-angle bins.

    ``frames``: evaluated frames (``evaluate.frame_errors``) of one setting with ``method, success, e_rot_rad,
    e_pos_gt_scale_m, overlap_gt, view_angle_gt``. Returns a 3x2 figure: rows rotation and translation error
    (log axes: the methods differ by orders of magnitude; boxes of the frames with an estimate), success rate
    (a method that never succeeds in a bin has no box there); columns overlap / angle bins, ``n`` frames per method.
    """
    import seaborn as sns

    plt = _plt()
    if frames.empty:
        raise PlotError("error_analysis_figure: no frames")
    df = frames.copy()
    cols = {"overlap": ("overlap_gt", overlap_bins, "ground-truth overlap ratio"),
            "angle": ("view_angle_gt", angle_bins, "relative viewing angle (rad)")}
    edge = lambda v: "π" if abs(v - np.pi) < 1e-9 else f"{v:g}"  # noqa: E731
    for key, (src, edges, _) in cols.items():
        labels = [f"{edge(a)}–{edge(b)}" for a, b in zip(edges[:-1], edges[1:])]
        df[key] = pd.cut(df[src], list(edges), include_lowest=True, labels=labels)
    methods = _methods_present(df)
    df["Method"] = df["method"].map(lambda m: SHORT_LABELS.get(m, m))
    order = [SHORT_LABELS.get(m, m) for m in methods]
    palette = {SHORT_LABELS.get(m, m): METHOD_COLORS.get(m, "gray") for m in methods}
    fig, axes = plt.subplots(3, 2, figsize=(13, 9.5), sharey="row", sharex="col",
                             gridspec_kw={"height_ratios": [1, 1, 0.7]})
    ok = df[df["success"].astype(bool)].copy()
    for y in ("e_rot_rad", "e_pos_gt_scale_m"):  # log axes: an exact zero sits at the floor
        ok[y] = ok[y].clip(lower=1e-6)
    drawn = [key for key, (src, _, _) in cols.items() if df[src].notna().any()]
    for c, (key, (src, _, xlabel)) in enumerate(cols.items()):
        cats = list(df[key].cat.categories)
        if key not in drawn:  # off, not cleared: the row's other panel shares this y axis
            for r in range(3):
                axes[r, c].axis("off")
            axes[0, c].text(0.5, 0.5, f"no {xlabel} in this setting", transform=axes[0, c].transAxes, ha="center")
            continue
        rows = (("e_rot_rad", "rotation error (rad, log)"),
                ("e_pos_gt_scale_m", "translation error,\nGT scale (m, log)"), (None, "success (%)"))
        for r, (y, lab) in enumerate(rows):
            ax = axes[r, c]
            if y is None:
                rate = df.groupby([key, "Method"], observed=False)["success"].mean().mul(100).rename("s").reset_index()
                sns.barplot(data=rate, x=key, y="s", hue="Method", hue_order=order, order=cats, palette=palette,
                            ax=ax, legend=False)
                ax.set_ylim(0, 100)
            elif ok[key].notna().any():
                sns.boxplot(data=ok, x=key, y=y, hue="Method", hue_order=order, order=cats, palette=palette,
                            ax=ax, showfliers=False, linewidth=0.8, log_scale=(False, True), legend=False)
                ax.grid(axis="y", which="major", alpha=0.3)
            ax.set_ylabel(lab if key == drawn[0] else "")
            ax.tick_params(labelleft=key == drawn[0])
            ax.yaxis.label.set_visible(key == drawn[0])
            ax.set_xlabel("")
        n = df.groupby([key, "method"], observed=False).size().groupby(level=0, observed=False).max()
        axes[2, c].set_xticks(range(len(cats)))
        axes[2, c].set_xticklabels([f"{cat}\nn={int(n.get(cat, 0))}" for cat in cats], fontsize=8)
        axes[2, c].set_xlabel(f"{xlabel}  (n: frames per method)")
    for ax in axes[:2].ravel():
        if ax.get_yscale() == "log":
            _plain_log_ticks(ax.yaxis)
    handles = [plt.Rectangle((0, 0), 1, 1, color=palette[m]) for m in order]
    fig.legend(handles, order, loc="upper center", ncol=len(order), frameon=False, bbox_to_anchor=(0.5, 0.965))
    fig.suptitle(title, y=0.995)
    fig.tight_layout(rect=(0, 0, 1, 0.94))
    return fig


# --------------------------------------------------------------------------- qualitative
def _plane_axes(P: np.ndarray) -> tuple[int, int]:
    """The two world axes with the largest spread (a bird's-eye view without knowing 'up')."""
    spread = np.nanstd(P.reshape(-1, 3), axis=0)
    a, b = np.argsort(spread)[::-1][:2]
    return int(min(a, b)), int(max(a, b))


def _camera_positions(df: pd.DataFrame, prefix: str, gt_scale: bool = False) -> np.ndarray:
    """``[T,3]`` position of the collaborator's camera in the ego camera frame (``T_ci_cj`` translation)
    from the ``<prefix>_t*, <prefix>_q*`` columns of ``T_cj_ci``; NaN rows where there is no pose.
    ``gt_scale``: translation direction with the ground-truth norm (scale-free methods)."""
    from .geometry import gt_scale_translation, se3_from_tq_xyzw, se3_inverse

    v = df[[f"{prefix}_{c}" for c in ("tx", "ty", "tz", "qx", "qy", "qz", "qw")]].to_numpy(float)
    if gt_scale:
        v[:, :3] = gt_scale_translation(v[:, :3], df[["gt_tx", "gt_ty", "gt_tz"]].to_numpy(float))
    ok = np.all(np.isfinite(v), axis=1)
    out = np.full((len(v), 3), np.nan)
    if ok.any():
        out[ok] = se3_inverse(se3_from_tq_xyzw(v[ok, :3], v[ok, 3:]))[:, :3, 3]
    return out


def qualitative_figure(traj_world: Mapping[str, np.ndarray], overlap: np.ndarray | None,
                       rel: Mapping[str, pd.DataFrame], ego: str, other: str,
                       images: Sequence[tuple[str, np.ndarray, np.ndarray]] = (), title: str = "",
                       overlap_threshold: float = 0.05,
                       metric_methods: Sequence[str] = ("cerpe", "cerpe-wo-em", "cerpe-graph")):
    """Collaborator position in the ego frame, bird's-eye view of both trajectories, image pairs.

    Args:
        traj_world: robot id -> ``[T,3]`` ground-truth camera positions (shared world frame).
        overlap: ``[T]`` ground-truth overlap ratio of the pair (or None).
        rel: method -> frame with ``step, est_tx, est_ty, est_tz, est_q*, gt_t*, gt_q*`` of
            the pair ``(ego, other)``; estimates of ``T_cj_ci``.
        images: ``(caption, image_ego, image_other)`` pairs to show in the bottom row.
    Methods that track the pair over time (``metric_methods``) are drawn as lines, the per-frame
    baselines as dots (consecutive estimates of theirs are independent); legends sit under the panels.
    """
    plt = _plt()
    n_img = len(images)
    fig = plt.figure(figsize=(13, 6.2 + (2.6 if n_img else 0)))
    gs = fig.add_gridspec(2 if n_img else 1, max(2, 2 * max(n_img, 1)), height_ratios=[2.4, 1] if n_img else [1])
    ax_rel = fig.add_subplot(gs[0, : gs.ncols // 2])
    ax_bev = fig.add_subplot(gs[0, gs.ncols // 2:])
    P = np.stack([np.asarray(v, float) for v in traj_world.values()])
    a, b = _plane_axes(P)
    for k, (rid, p) in enumerate(traj_world.items()):
        p, colour = np.asarray(p, float), ["tab:orange", "black", "tab:blue"][k % 3]
        ax_bev.plot(p[:, a], p[:, b], "-", color=colour, label=f"{rid}" + (" (ego)" if rid == ego else ""))
        ax_bev.plot(p[0, a], p[0, b], "o", color=colour, ms=5)
        if overlap is not None and rid in (ego, other):
            ov = np.asarray(overlap) > overlap_threshold
            ax_bev.scatter(p[ov, a], p[ov, b], s=14, color="tab:green", zorder=3,
                           label=f"overlap > {overlap_threshold:g}" if rid == ego and ov.any() else None)
            ax_bev.scatter(p[~ov, a], p[~ov, b], s=14, facecolors="none", edgecolors="gray", zorder=3,
                           label="no overlap" if rid == ego and (~ov).any() else None)
    ax_bev.set_aspect("equal", "datalim")
    ax_bev.set_title("ground truth, bird's-eye view (start = dot)", fontsize=10)
    ax_bev.set_xlabel(f"world {'xyz'[a]} (m)")
    ax_bev.set_ylabel(f"world {'xyz'[b]} (m)")
    _legend_below(ax_bev, ncol=3, fontsize=8)
    g = _camera_positions(next(iter(rel.values())), "gt")
    ax_rel.plot(g[:, 0], g[:, 2], "k.-", lw=1.2, ms=5, label="ground truth", zorder=4)
    for m, df in rel.items():
        e = _camera_positions(df, "est", gt_scale=m not in metric_methods)
        if np.isfinite(e).any():
            ax_rel.plot(e[:, 0], e[:, 2], ".-" if m in metric_methods else "o", color=METHOD_COLORS.get(m, "gray"),
                        lw=0.9, ms=4 if m in metric_methods else 3, alpha=0.85, label=SHORT_LABELS.get(m, m))
    ax_rel.plot([0], [0], marker="^", color="tab:orange", ms=10, ls="none", label=f"ego camera {ego}")
    ax_rel.set_aspect("equal", "datalim")
    ax_rel.set_xlabel("x in ego camera (m, right)")
    ax_rel.set_ylabel("z in ego camera (m, forward)")
    ax_rel.set_title(f"position of {other} in {ego}'s camera frame\n(CERPE rows: predicted scale; "
                     "per-frame baselines: dots, GT scale)", fontsize=10)
    _legend_below(ax_rel, ncol=3, fontsize=8)
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
                         paper: Mapping[str, float] | None = None, title: str = "", runtime_source: str = ""):
    """Bytes per robot per step, gate activations of one pair over time, latency per team step.

    Args: ``bytes_table``: ``scheme, bytes_per_robot_step`` (mean); ``gate``: ``step, gate_score,
    gate_open, overlap_gt`` of one pair, ``attrs`` ``label`` (which pair, why that one) and ``tau``;
    ``latency``: ``n_robots`` (int or ``"N (settings)"``), ``stage``, ``seconds`` (mean per team step);
    ``paper``: the paper's own figures (descriptor KB, image KB, ``ms_2``/``ms_3``); ``runtime_source``:
    where the latencies were measured (``cerpe bench`` alone, or the runs: how many on how many cores).
    """
    import textwrap

    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(16, 5.2), gridspec_kw={"width_ratios": [1.05, 1.1, 1]})
    ax = axes[0]
    kb = bytes_table["bytes_per_robot_step"].to_numpy(float) / 1000.0
    ys = np.arange(len(kb))[::-1]
    ax.barh(ys, kb, color=(["tab:green", "tab:red"] + ["tab:brown"] * (len(kb) - 3) + ["tab:gray"])[-len(kb):])
    for y, v in zip(ys, kb):
        ax.text(v, y, f" {v:.1f} KB", va="center", fontsize=8)
    ax.set_yticks(ys)
    ax.set_yticklabels([textwrap.fill(str(s), 24) for s in bytes_table["scheme"]], fontsize=8)
    ax.set_xlabel("KB per robot per step (mean, this run)")
    ax.set_xlim(0, 1.25 * max(np.nanmax(kb), 1e-3))
    if paper:
        ax.set_title(f"paper (VGGT/SALAD): descriptor {paper['descriptor_kb']} KB,\n"
                     f"one 640x480 JPEG {paper['image_kb']} KB", fontsize=8)
    ax = axes[1]
    if not gate.empty:
        ax.fill_between(gate["step"], 0, 1, where=gate["gate_open"].astype(bool).to_numpy(), step="mid",
                        transform=ax.get_xaxis_transform(), color="tab:red", alpha=0.12, lw=0,
                        label="gate open (image requested)")
        ax.plot(gate["step"], gate["gate_score"], ".-", color="tab:blue", lw=1, ms=3,
                label="descriptor cosine, this frame")
        if "overlap_gt" in gate and gate["overlap_gt"].notna().any():
            ax.plot(gate["step"], gate["overlap_gt"], "--", color="tab:green", lw=1, label="GT overlap ratio")
        if "tau" in gate.attrs:
            ax.axhline(gate.attrs["tau"], color="k", lw=0.7, ls=":", label=f"tau = {gate.attrs['tau']:.3f}")
        _legend_below(ax, ncol=2)
    ax.set_xlabel("step")
    ax.set_ylabel("cosine / overlap ratio")
    ax.set_title("\n".join(textwrap.fill(ln, 62) for ln in gate.attrs.get("label", "gate activations").split("\n")),
                 fontsize=8)
    ax = axes[2]
    if not latency.empty:
        lat = latency.assign(n_robots=latency["n_robots"].map(lambda v: int(str(v).split()[0])))  # "2 (a, b)"
        piv = lat.pivot_table(index="n_robots", columns="stage", values="seconds", aggfunc="mean").fillna(0.0) * 1000
        piv = piv.loc[:, piv.max() > 0]
        x = np.arange(len(piv))
        bottom = np.zeros(len(piv))
        for st in piv.columns:
            ax.bar(x, piv[st].to_numpy(), 0.6, bottom=bottom, label=st)
            bottom += piv[st].to_numpy()
        ref = [(xi, paper[f"ms_{n}"]) for xi, n in zip(x, piv.index) if paper and f"ms_{n}" in paper]
        for xi, v in zip(x, bottom):  # above the bar and above the paper's mark on it
            ax.text(xi, max([v] + [r * 1.06 for xr, r in ref if xr == xi]), f"{v:.0f} ms", ha="center",
                    va="bottom", fontsize=8)
        for k, (xi, v) in enumerate(ref):
            ax.hlines(v, xi - 0.3, xi + 0.3, color="black", lw=2, zorder=4,
                      label="paper (RTX 4080 laptop, VGGT)" if k == 0 else None)
            ax.text(xi + 0.32, v, f"{v:.0f}", va="center", fontsize=7)
        ax.set_xticks(x)
        ax.set_xticklabels([f"{n} robots" for n in piv.index])
        ax.set_ylim(0, 1.18 * max([bottom.max(), 1e-3] + [v for _, v in ref]))
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    ax.set_ylabel("ms per team step (mean, all robots, CPU)")
    ax.set_title(textwrap.fill(runtime_source or "measured while the runs were made", 48), fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def gate_example_setting(table: pd.DataFrame) -> tuple[str, str]:
    """The setting whose gate a figure illustrates, and the rule that chose it: the one with the
    highest ROC AUC against co-visibility (``covis_roc_auc``; the ordered label's ``roc_auc`` where
    that is undefined); the first setting when no AUC is defined."""
    if table.empty:
        raise PlotError("gate table: no settings")
    auc = pd.to_numeric(table.get("covis_roc_auc", pd.Series(np.nan, index=table.index)), errors="coerce")
    auc = auc.fillna(pd.to_numeric(table.get("roc_auc", np.nan), errors="coerce"))
    if not auc.notna().any():
        return str(table["setting"].iloc[0]), "the first (no gate ROC AUC defined)"
    k = auc.idxmax()
    return str(table.loc[k, "setting"]), f"highest gate ROC AUC ({auc[k]:.3f})"


def gate_example_pair(steps: pd.DataFrame, setting: str = "", tau: float | None = None) -> pd.DataFrame:
    """One ordered pair's gate over time, from a CERPE run's ``steps.csv`` rows (one setting): the pair
    whose gate is most both open and shut (largest min(open steps, shut steps); ties: the first), so the
    panel shows the gate deciding. Columns ``step, gate_score, gate_open, overlap_gt``; ``attrs`` label, tau."""
    if steps.empty:
        raise PlotError(f"gate example: no steps for {setting or 'the setting'}")
    opened = steps.groupby(["encounter", "ego", "other"])["gate_open"].agg(["sum", "size"])
    enc, ego, other = (opened["sum"].clip(upper=opened["size"] - opened["sum"])).idxmax()
    g = steps[(steps["encounter"] == enc) & (steps["ego"] == ego) & (steps["other"] == other)]
    g = g[["step", "gate_score", "gate_open", "overlap_gt"]].sort_values("step").reset_index(drop=True)
    g.attrs["label"] = f"gate of {ego} about {other} ({'/'.join(x for x in (setting, enc) if x)})"
    if tau is not None and np.isfinite(tau):
        g.attrs["tau"] = float(tau)
    return g


def gate_figure(curves: Mapping[str, tuple[np.ndarray, np.ndarray]], table: pd.DataFrame, points: pd.DataFrame,
                overlap: float = 0.2, title: str = "",
                curves_covis: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None):
    """The descriptor gate against ground-truth overlap: ROC per setting, and cosine vs overlap.

    Args: ``curves``/``curves_covis``: ``{setting: (fpr, tpr)}`` with the ordered label (dashed) and the
    co-visibility label of unordered pairs (solid: overlap >= ``overlap`` both ways positive, < 0.05 both
    ways negative); ``table``: ``setting, roc_auc, tau, precision, recall`` (and ``roc_auc_ceiling``,
    ``covis_roc_auc, covis_precision, covis_recall`` when present); ``points``: ``setting, gate_score,
    overlap_gt``. One colour per setting in both panels; the legends sit under the panels.
    """
    plt = _plt()
    names = dict.fromkeys(list(table["setting"]) + list(points["setting"]))
    colours = {s: plt.get_cmap("tab10")(k % 10) for k, s in enumerate(names)}
    fig, axes = plt.subplots(1, 2, figsize=(12, 6))
    ax = axes[0]
    for s, (fpr, tpr) in (curves_covis or {}).items():
        r = table[table["setting"] == s].iloc[0]
        ax.plot(fpr, tpr, lw=1.5, color=colours.get(s), label=f"{s}, co-visibility label: AUC "
                f"{r['covis_roc_auc']:.3f}, P {r['covis_precision']:.2f} / R {r['covis_recall']:.2f} at tau")
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
    ax.set_title(f"gate ROC, descriptor cosine vs GT co-visibility\nsolid: unordered pairs (overlap >= {overlap:g} "
                 f"both ways vs < 0.05 both ways)\ndashed: ordered pairs (overlap >= {overlap:g})", fontsize=8)
    if ax.get_lines()[:-1]:
        _legend_below(ax, ncol=1, fontsize=6.5)
    ax = axes[1]
    for s, g in points.groupby("setting", sort=False):
        ax.scatter(g["overlap_gt"], g["gate_score"], s=4, alpha=0.35, color=colours.get(s), label=s)
    for tau in table["tau"].dropna().unique():
        ax.axhline(tau, color="k", lw=0.7, ls=":", label=f"tau = {tau:.3f}")
    ax.axvline(overlap, color="tab:red", lw=0.7, ls="--", label=f"overlap = {overlap:g}")
    ax.set_xlabel("ground-truth overlap ratio")
    ax.set_ylabel("descriptor cosine (fp16 wire)")
    ax.set_title("every ordered pair and step", fontsize=8)
    _legend_below(ax, ncol=3, fontsize=7, markerscale=3)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


# --------------------------------------------------------------------------- uncertainty calibration
def calibration_figure(frames: pd.DataFrame, table: pd.DataFrame, title: str = ""):
    """Error against predicted sigma, position and rotation, per method with a covariance.

    ``frames``: evaluated frames of one setting with ``method, success, e_pos_m, e_rot_rad, sigma_pos_m,
    sigma_rot_rad``; ``table``: :func:`cerpe.pipeline.evaluate.sigma_calibration` rows of that setting.
    Returns a 1x2 figure: each frame's error against its predicted sigma (dots), the RMS error per bin of
    predicted sigma against the bin's RMS sigma (line), and the ideal ``y = x``.
    """
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.8))
    for ax, (quantity, err, sig, unit) in zip(axes, (("position", "e_pos_m", "sigma_pos_m", "m"),
                                                     ("rotation", "e_rot_rad", "sigma_rot_rad", "rad"))):
        ok = frames[frames["success"].astype(bool)] if "success" in frames else frames
        ok = ok[np.isfinite(pd.to_numeric(ok[sig], errors="coerce"))] if sig in ok else ok.iloc[0:0]
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
        ax.set_title(quantity)
        if top <= 0:  # say why the panel is empty, without meaningless 0..1 ticks
            ax.set(xticks=[], yticks=[])
            ax.text(0.5, 0.5, "no estimate with a covariance in this setting", transform=ax.transAxes, ha="center")
            continue
        ax.plot([0, top], [0, top], ":", color="0.4", lw=1, label="calibrated (error = sigma)")
        _legend_below(ax, ncol=1, fontsize=7)
        ax.set_xlabel(f"predicted sigma ({unit}; sqrt of the covariance trace)")
        ax.set_ylabel(f"{quantity} error ({unit})")
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def message_loss_figure(summary: pd.DataFrame, title: str = ""):
    """Success and errors against the fraction of messages (wire frames) lost: a 1x4 figure, one line per
    method, one legend over the panels. ``summary``: :func:`cerpe.pipeline.message_loss.main`'s rows
    (``method, loss, success_pct, success_after_covis_pct, e_rot_rad, e_pos_m``)."""
    if summary.empty:
        raise PlotError("message-loss figure: no rows")
    plt = _plt()
    fig, axes = plt.subplots(1, 4, figsize=(15, 3.9))
    panels = (("success_pct", "success (%)"), ("success_after_covis_pct", "success after co-visibility (%)"),
              ("e_rot_rad", "mean e_rot (rad)"), ("e_pos_m", "mean e_pos (m)"))
    for ax, (col, label) in zip(axes, panels):
        for m in [m for m in METHOD_ORDER if m in set(summary["method"])]:
            f = summary[summary["method"] == m].sort_values("loss")
            ax.plot(100 * f["loss"], f[col], "o-", color=METHOD_COLORS.get(m, "gray"), label=SHORT_LABELS.get(m, m))
        ax.set_xlabel("messages lost (%)")
        ax.set_ylabel(label)
        if col.endswith("pct"):
            ax.set_ylim(0, 105)
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=len(labels), frameon=False, bbox_to_anchor=(0.5, 0.94))
    fig.suptitle(title, y=0.99)
    fig.tight_layout(rect=(0, 0, 1, 0.9))
    return fig


def pareto_figure(table: pd.DataFrame, setting: str = "all", title: str = ""):
    """Bytes per robot per step against e_rot and against e_pos, one point per scheme of ``setting``
    (``table``: :func:`cerpe.pipeline.pareto.pareto_table` rows). A 1x2 figure (log bytes axis, plain
    numbers), one legend under both panels; a scheme without a metric position (per-frame baselines) is
    left out of the e_pos panel, whose title says so."""
    plt = _plt()
    t = table[table["setting"] == setting]
    if not len(t):
        raise PlotError(f"pareto figure: no rows for setting {setting!r}")
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.6))
    cmap = plt.get_cmap("tab10")
    for ax, (col, name) in zip(axes, (("e_rot_rad", "rotation error e_rot (rad)"),
                                      ("e_pos_m", "position error e_pos (m)"))):
        left_out = []
        for k, (_, r) in enumerate(t.iterrows()):
            x, y = float(r["bytes_per_robot_step"]), float(r[col])
            if not (np.isfinite(x) and np.isfinite(y) and x > 0):
                left_out.append(str(r["scheme"]))
                continue
            ax.scatter([x / 1000], [y], s=40, color=cmap(k % 10), label=f"{r['scheme']}: {r['label']}", zorder=3)
            ax.annotate(str(r["scheme"]), (x / 1000, y), textcoords="offset points", xytext=(4, 4), fontsize=7)
        ax.set_xscale("log")
        ax.margins(x=0.12, y=0.1)
        _plain_log_ticks(ax.xaxis)
        ax.set_xlabel("KB per robot per step (log axis)")
        ax.set_ylabel(f"mean {name}")
        ax.set_title(name + ("" if not left_out else f"\nnot shown (no metric value): {', '.join(left_out)}"),
                     fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
    handles = {}
    for ax in axes:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(lab, h)
    fig.legend(list(handles.values()), list(handles), loc="lower center", ncol=2, fontsize=7, frameon=False)
    fig.suptitle(title or f"bytes vs accuracy ({setting})")
    fig.tight_layout(rect=(0, 0.14, 1, 1))
    return fig
