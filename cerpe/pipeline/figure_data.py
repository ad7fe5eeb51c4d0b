"""What the notebooks' figures and tables plot, from a :class:`~cerpe.pipeline.paper_context.PaperContext`'s runs:
the qualitative figure, communication and runtime, the gate against ground-truth overlap, and
the calibration of the graph's covariances (their plotting: :mod:`cerpe.plotting`).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pandas as pd

from ..atomicio import read_json
from ..methods import BASELINE_METHODS, METHOD_LABELS
from ..runfolder.layout import RUN_JSON
from ..runfolder.read import gate_tau
from .evaluate import GATE_OVERLAP, covisibility_pairs, gate_quality, roc_curve, sigma_calibration
from .paper_context import PaperContext, frames
from .paper_settings import PaperError, ensure_loaded

# The paper's own systems figures (Section IV, RTX 4080 laptop, VGGT/SALAD): never our measurements.
PAPER_NUMBERS: dict[str, float] = {"descriptor_kb": 16.9, "image_kb": 26, "ms_2": 438, "ms_3": 780}


def qualitative_data(ctx: PaperContext, setting: str, encounter: str | None = None,
                     methods: Sequence[str] = ("cerpe", "cerpe-wo-em", "cerpe-graph", "aliked-lightglue",
                                               "sift-ransac")) -> dict:
    """Inputs of :func:`cerpe.plotting.qualitative_figure` for one encounter of a setting.

    Picks the encounter with the most steps that have both overlapping and
    non-overlapping moments (first encounter otherwise), its first ordered pair,
    and one overlapping and one non-overlapping image pair.
    """
    entry = next((e for e in ctx.settings if e.name == setting and e.status == "ok"), None)
    if entry is None:
        raise PaperError(f"setting {setting!r} has no data in this profile")
    if not ensure_loaded(entry):
        raise PaperError(f"setting {setting!r}: {entry.detail}")
    encs = {e.name: e for e in entry.setting.encounters}
    if encounter is None:
        def mixed(e: Any) -> float:
            if e.overlap is None:
                return 0.0
            ov = e.overlap[:, 0, 1] > 0.05
            return float(ov.any() and (~ov).any()) * e.n_steps
        encounter = max(encs.values(), key=mixed).name
    enc = encs[encounter]
    i, j = 0, 1
    ego, other = enc.robots[i].robot_id, enc.robots[j].robot_id
    rel = {}
    for m in methods:
        p = ctx.run_dirs.get((setting, m))
        if p is None:
            continue
        f = pd.read_csv(p / encounter / "steps.csv")
        rel[m] = f[(f["ego"] == ego) & (f["other"] == other)].sort_values("step").reset_index(drop=True)
    traj = {r.robot_id: r.T_world_cam[:, :3, 3] for r in enc.robots}
    overlap = enc.overlap[:, i, j] if enc.overlap is not None else None
    imgs = []
    if overlap is not None:
        ov_steps = np.flatnonzero(overlap > 0.05)
        no_steps = np.flatnonzero(overlap <= 0.05)
        if len(ov_steps):
            t = int(ov_steps[np.argmax(overlap[ov_steps])])
            imgs.append((f"overlap {overlap[t]:.2f}, step {t}", enc.robots[i].image(t), enc.robots[j].image(t)))
        if len(no_steps):
            t = int(no_steps[len(no_steps) // 2])
            imgs.append((f"no overlap, step {t}", enc.robots[i].image(t), enc.robots[j].image(t)))
    else:
        t = enc.n_steps // 2
        imgs.append((f"step {t}", enc.robots[i].image(t), enc.robots[j].image(t)))
    return {"traj_world": traj, "overlap": overlap, "rel": rel, "ego": ego, "other": other, "images": imgs,
            "title": f"{setting} / {encounter}"}


def communication_data(ctx: PaperContext, method: str = "cerpe") -> dict:
    """Inputs of :func:`cerpe.plotting.communication_figure` plus a summary table.

    * bytes per robot and step: descriptor + pose messages only; CERPE as run
      (descriptors + gated image requests/replies); "always send images"
      (descriptor + pose + one JPEG reply to every other robot, every step, the
      per-frame baselines' requirement), from the same images' JPEG sizes.
    * gate activations of the first pair of the encounter with the most openings.
    * per-stage latency (seconds per team step: all robots' updates, run one after
      the other on this machine) for 2- and 3-robot encounters.
    """
    robots, steps = [], []
    for (s, m), p in ctx.run_dirs.items():
        if m != method:
            continue
        for enc_dir in sorted(d for d in p.iterdir() if (d / "DONE.json").exists()):
            r = pd.read_csv(enc_dir / "robots.csv")
            st = pd.read_csv(enc_dir / "steps.csv")
            n = st["ego"].nunique()
            r["setting"], r["n_robots"] = s, n
            st["setting"], st["n_robots"] = s, n
            robots.append(r)
            steps.append(st)
    if not robots:
        raise PaperError(f"no finished {method} runs under {ctx.runs_root}")
    R = pd.concat(robots, ignore_index=True)
    S = pd.concat(steps, ignore_index=True)
    desc = (R["bytes_descriptor"] + R["bytes_pose"]).mean()
    gated = R["bytes_total"].mean()
    # an image reply as CERPE sent it, else the baselines' JPEG of the same frames
    pair_reply = S.loc[S["bytes_pair"] > 0, "bytes_pair"]
    img = float(pair_reply.mean()) if len(pair_reply) else float("nan")
    if not np.isfinite(img):
        for (s, m), p in ctx.run_dirs.items():
            if m in BASELINE_METHODS:
                b = pd.concat(pd.read_csv(d / "steps.csv") for d in p.iterdir() if (d / "DONE.json").exists())
                img = float(b["bytes_pair"].mean())
                break
    always = desc + img * (S.groupby(["setting", "encounter"])["n_robots"].first().mean() - 1)
    schemes = [("descriptor + pose only", desc), (f"{METHOD_LABELS[method]} (gated images)", gated)]
    graph = _robot_rows(ctx, "cerpe-graph") if method != "cerpe-graph" else pd.DataFrame()
    if len(graph):  # the extension sends the same messages: its bar shows that
        schemes.append(("CERPE + pose graph (ours; gated images, same messages)", float(graph["bytes_total"].mean())))
    schemes.append(("always send images", always))
    bytes_table = pd.DataFrame({"scheme": [n for n, _ in schemes], "bytes_per_robot_step": [v for _, v in schemes]})
    opens = S.groupby(["setting", "encounter", "ego", "other"])["gate_open"].sum()
    key = opens.idxmax()
    gate = S[(S["setting"] == key[0]) & (S["encounter"] == key[1]) & (S["ego"] == key[2]) & (S["other"] == key[3])]
    gate = gate[["step", "gate_score", "gate_open", "overlap_gt"]].sort_values("step").reset_index(drop=True)
    gate.attrs["label"] = f"gate of {key[2]} about {key[3]} ({key[0]}/{key[1]})"
    tau = _run_tau(ctx.run_dirs[(key[0], method)], "cerpe")
    if tau is not None:
        gate.attrs["tau"] = float(tau)
    stage_cols = [c for c in R.columns if c.startswith("t_") and c.endswith("_s")]
    # The paper's 438/780 ms are one update of the whole team on one laptop; our robots
    # also run one after the other in one process, so a team step is the sum over robots.
    team = R.groupby(["setting", "encounter", "step", "n_robots"], as_index=False)[stage_cols].sum()
    lat = team.melt(id_vars=["n_robots"], value_vars=stage_cols, var_name="stage", value_name="seconds")
    lat["stage"] = lat["stage"].str[2:-2]
    lat = lat.groupby(["n_robots", "stage"], as_index=False)["seconds"].mean()
    # encounters of different sizes come from different settings (image sizes, scenes): say which
    where = R.groupby("n_robots")["setting"].agg(lambda v: ", ".join(sorted(set(v))))
    lat["n_robots"] = lat["n_robots"].map(lambda n: f"{n} ({where[n]})")
    summary = pd.DataFrame({
        "quantity": ["descriptor+pose message bytes / robot / step", "CERPE bytes / robot / step",
                     "always-send-images bytes / robot / step", "gate open rate (pairs)",
                     "image replies sent / robot / step"]
                    + [f"latency per team step, {n} robots (ms)" for n in sorted(lat["n_robots"].unique())],
        "this run": [desc, gated, always, float(S["gate_open"].mean()), float((R["bytes_reply"] > 0).mean())]
                    + [1000 * lat[lat["n_robots"] == n]["seconds"].sum() for n in sorted(lat["n_robots"].unique())],
    })
    paper_col = {0: PAPER_NUMBERS["descriptor_kb"] * 1000, 2: np.nan}
    if len(graph) and "t_graph_s" in graph:  # the graph update of cerpe-graph per robot-step
        ms = 1000 * graph["t_graph_s"].to_numpy(float)
        summary = pd.concat([summary, pd.DataFrame({
            "quantity": ["CERPE + pose graph bytes / robot / step", "graph update per robot-step, median (ms)",
                         "graph update per robot-step, p90 (ms)"],
            "this run": [float(graph["bytes_total"].mean()), float(np.median(ms)), float(np.percentile(ms, 90))]})],
            ignore_index=True)
    summary["paper (RTX 4080 laptop, VGGT)"] = [paper_col.get(k, np.nan) for k in range(len(summary))]
    for k, q in enumerate(summary["quantity"]):
        if q.startswith("latency per team step, 2 "):
            summary.loc[k, "paper (RTX 4080 laptop, VGGT)"] = PAPER_NUMBERS["ms_2"]
        if q.startswith("latency per team step, 3 "):
            summary.loc[k, "paper (RTX 4080 laptop, VGGT)"] = PAPER_NUMBERS["ms_3"]
    return {"bytes_table": bytes_table, "gate": gate, "latency": lat, "summary": summary,
            "paper": PAPER_NUMBERS, "image_bytes": img}


def _robot_rows(ctx: PaperContext, method: str) -> pd.DataFrame:
    """``robots.csv`` rows of every finished encounter of ``method``'s runs (empty when none)."""
    rows = [pd.read_csv(d / "robots.csv") for (s, m), p in sorted(ctx.run_dirs.items()) if m == method and p.is_dir()
            for d in sorted(p.iterdir()) if (d / "DONE.json").exists()]
    return pd.concat(rows, ignore_index=True) if rows else pd.DataFrame()


def calibration_data(ctx: PaperContext, n_bins: int = 6) -> dict:
    """Inputs of :func:`cerpe.plotting.calibration_figure` per setting: ``{"frames": {setting: frames},
    "table": sigma_calibration rows of every setting}`` over the methods whose runs carry a covariance."""
    f = frames(ctx)
    f = f[f["method"].isin([m for m in f["method"].unique()
                            if "sigma_pos_m" in f and np.isfinite(f.loc[f["method"] == m, "sigma_pos_m"]).any()])]
    return {"frames": {e.name: f[f["setting"] == e.name] for e in ctx.ok_settings},
            "table": sigma_calibration(f, n_bins)}


def _run_tau(run_dir: Path, method: str) -> float | None:
    """The gate threshold a CERPE run used (``run.json``), or None."""
    return gate_tau(read_json(run_dir / RUN_JSON, RUN_JSON))


def gate_data(ctx: PaperContext, method: str = "cerpe") -> dict:
    """Descriptor gate vs ground-truth overlap per setting, from CERPE's ``steps.csv``.

    Returns:
        ``table``: one row per setting with :func:`~cerpe.pipeline.evaluate.gate_quality`'s
        fields: the co-visibility label of unordered pairs (``covis_*``: ROC AUC, precision
        and recall at the run's ``tau``) and, beside it, the old ordered label (ROC AUC of
        the cosine against ``overlap_gt >= 0.2`` over all ordered pairs and steps, precision
        and recall at ``tau``, open rate, the symmetric-score ceiling);
        ``curves_covis`` and ``curves``: ``{setting: (fpr, tpr)}`` of the two labels;
        ``points``: ``setting, gate_score, overlap_gt`` rows for a scatter; ``overlap``: the
        label threshold.
    """
    rows, curves, curves_covis, points = [], {}, {}, []
    for (s, m), p in sorted(ctx.run_dirs.items()):
        if m != method:
            continue
        done = [d for d in sorted(p.iterdir()) if (d / "DONE.json").exists()]
        if not done:
            continue
        S = pd.concat([pd.read_csv(d / "steps.csv") for d in done], ignore_index=True)
        q = gate_quality(S, _run_tau(p, method))
        rows.append({"setting": s, **q})
        ok = S["gate_score"].notna() & S["overlap_gt"].notna()
        if q["n_overlapping"] and q["n_overlapping"] < q["n_pairs"]:
            fpr, tpr, _ = roc_curve(S.loc[ok, "gate_score"], S.loc[ok, "overlap_gt"] >= GATE_OVERLAP)
            curves[s] = (fpr, tpr)
        cp = covisibility_pairs(S)
        cp = cp[cp["gate_score"].notna() & cp["label"].notna()]
        if 0 < q["covis_n_positive"] < q["covis_n_pairs"]:
            fpr, tpr, _ = roc_curve(cp["gate_score"], cp["label"] > 0.5)
            curves_covis[s] = (fpr, tpr)
        points.append(S.loc[ok, ["gate_score", "overlap_gt"]].assign(setting=s))
    if not rows:
        raise PaperError(f"no finished {method} runs under {ctx.runs_root}")
    return {"table": pd.DataFrame(rows), "curves": curves, "curves_covis": curves_covis, "overlap": GATE_OVERLAP,
            "points": pd.concat(points, ignore_index=True)}
