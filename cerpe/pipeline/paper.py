"""Build every table and figure of the paper (what ``make paper`` runs).

Usage: ``cerpe paper [--models offline|paper] [--suite paper-default|fixture] [--jobs N]``

1. every manifest in ``datasets_manifest/``: enabled ones are loaded (synthetic
   settings are generated on demand with the chosen suite); disabled ones are
   listed in Table I as "not supplied" with the manifest to fill;
2. every method runs on every enabled setting (``cerpe run``; cached in
   ``build/runs/<setting>/<method>/`` and resumed; a run of another
   configuration is replaced); the Pareto settings (:mod:`cerpe.pipeline.pareto`) run
   on the first encounter of each synthetic setting (``build/runs/<setting>/pareto-*``), and the
   message-loss sweep (``build/runs/synthetic-indoor/message-loss``); for paper-default these
   runs go to ``--jobs`` worker processes (:mod:`cerpe.pipeline.schedule`), same results;
3. the notebooks run with papermill into ``build/notebooks/`` and write
   ``tables/`` and ``figures/``. When the inputs' fingerprint (run
   fingerprints, notebooks, evaluation/plotting code, parameters) is unchanged
   and every output exists, the notebooks are not executed again.

``--models`` sets ``backbone.models`` of every CERPE run (``offline``: the stand-ins that run here;
``paper``: VGGT + SALAD/DINOv2 + Metric3Dv2 with user-supplied weights).
``--suite fixture`` is the tiny suite the tests use; it writes to
``build/fixture/{runs,figures,tables}`` and never touches the paper outputs.

The notebooks call the functions below (:func:`context`, :func:`qualitative_data`,
:func:`communication_data`, :func:`gate_data`), :mod:`cerpe.pipeline.table1` (Table I)
and :mod:`cerpe.plotting`.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import logging
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pandas as pd

from ..atomicio import atomic_write_json, atomic_write_text
from ..errors import CerpeError
from .evaluate import (GATE_OVERLAP, EvalError, covisibility_pairs, evaluate_runs, gate_quality, roc_curve,
                       sigma_calibration)
from .methods import BASELINE_METHODS, METHOD_LABELS, UNAVAILABLE
from .run import run_method
from .runcheck import gate_tau, run_is_current
from .table1 import EXPECTED_TABLES

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[2]
RUN_METHODS: tuple[str, ...] = ("cerpe", "cerpe-wo-em", "cerpe-graph", "sift-ransac", "aliked-lightglue")
# The paper's own systems figures (Section IV, RTX 4080 laptop, VGGT/SALAD): never our measurements.
PAPER_NUMBERS: dict[str, float] = {"descriptor_kb": 16.9, "image_kb": 26, "ms_2": 438, "ms_3": 780}
NOTEBOOKS: tuple[str, ...] = ("01_main_results", "02_error_analysis", "03_qualitative", "04_communication_runtime",
                              "05_uncertainty", "06_message_loss", "07_pareto")
# outputs each notebook must leave (stems; figures as .png and .pdf)
EXPECTED_FIGURES: tuple[str, ...] = ("error_analysis", "communication_runtime", "gate_quality", "calibration",
                                     "message_loss", "pareto")
NOTEBOOK_TABLES: tuple[str, ...] = ("communication_runtime.csv", "gate_quality.csv",  # written by notebook 04
                                    "calibration.csv",  # notebook 05
                                    "message_loss.csv", "message_loss.md",  # notebook 06
                                    "pareto.csv", "pareto.md")  # notebook 07
MODELS: tuple[str, ...] = ("offline", "paper")  # backbone.models of the CERPE runs
SYNTHETIC_ORDER = ("cad-intersection", "indoor-team")


class PaperError(CerpeError, ValueError):
    """The paper build cannot proceed (no manifests folder, unknown profile, failed notebook)."""


@dataclass
class SettingEntry:
    """One column group of Table I.

    ``status`` is ``ok``, ``not supplied`` (disabled manifest), ``skipped`` (a
    real dataset in the fixture profile) or ``error`` (with ``detail``).
    """

    name: str
    manifest: Path
    status: str
    detail: str = ""
    run_manifest: Path | None = None
    world: str = ""
    setting: Any = None


@dataclass
class PaperContext:
    profile: str
    suite: str
    models: str
    runs_root: Path
    figures_dir: Path
    tables_dir: Path
    notebooks_dir: Path
    settings: list[SettingEntry] = field(default_factory=list)
    run_dirs: dict[tuple[str, str], Path] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)
    extra_runs: list[Path] = field(default_factory=list)  # runs beside the methods' (the Pareto settings)

    @property
    def ok_settings(self) -> list[SettingEntry]:
        return [s for s in self.settings if s.status == "ok"]

    @property
    def sets(self) -> dict[str, Any]:
        """The knobs every CERPE run of the context sets besides its preset."""
        return {} if self.models == "offline" else {"backbone.models": self.models}

    def sets_of(self, method: str) -> dict[str, Any] | None:
        """:attr:`sets` for a CERPE method, None for a baseline."""
        from .methods import CERPE_METHODS

        return self.sets if method in CERPE_METHODS else None


def _layout(profile: str, models: str, root: Path) -> dict[str, Path]:
    if profile == "fixture":
        base = root / "build" / "fixture"
        return {"runs": base / "runs" / models, "figures": base / "figures", "tables": base / "tables",
                "notebooks": base / "notebooks", "manifests": base / "manifests"}
    if profile == "paper-default":
        runs = root / "build" / "runs" if models == "offline" else root / "build" / f"runs-{models}"
        return {"runs": runs, "figures": root / "figures", "tables": root / "tables",
                "notebooks": root / "build" / "notebooks", "manifests": root / "build" / "manifests" / profile}
    raise PaperError(f"unknown notebook profile {profile!r}; use 'fixture' or 'paper-default'")


def _derived_manifest(man: Any, suite: str, out_dir: Path) -> Path:
    """A synthetic manifest with its suite replaced, paths made absolute (original untouched)."""
    import yaml

    raw = dict(man.raw)
    if raw.get("suite", "paper-default") == suite:
        return Path(man.path)
    raw["suite"] = suite
    if raw.get("cache_dir"):
        raw["cache_dir"] = str(man.resolve(raw["cache_dir"]))
    if man.data_root is not None:
        raw["data_root"] = str(man.data_root)
    out = out_dir / f"{man.name}.yaml"
    atomic_write_text(out, yaml.safe_dump(raw, sort_keys=False))
    return out


def discover_settings(profile: str, suite: str, manifests_dir: Path, derived_dir: Path,
                      load: bool = True) -> list[SettingEntry]:
    """Every manifest as a Table I column group, synthetic ones first; loads enabled settings."""
    from ..datasets import ManifestError, disabled_reason, find_manifests, load_setting

    if not manifests_dir.is_dir():
        raise PaperError(f"manifest folder not found: {manifests_dir}")
    entries = []
    for man in find_manifests(manifests_dir):
        world = str(man.raw.get("world", "")) if man.adapter == "synthetic" else ""
        e = SettingEntry(man.name, Path(man.path), "ok", world=world)
        if not man.enabled:
            where = man.path.relative_to(ROOT) if man.path.is_relative_to(ROOT) else man.path
            e.status, e.detail = "not supplied", (disabled_reason(man) if man.enabled_if_present
                                                  else f"fill {where} and set enabled: true")
        elif man.adapter != "synthetic" and suite == "fixture":
            e.status, e.detail = "skipped", "real datasets are not run in the fixture suite"
        else:
            e.run_manifest = _derived_manifest(man, suite, derived_dir) if man.adapter == "synthetic" else Path(man.path)
            if load:
                try:
                    e.setting = load_setting(e.run_manifest)
                except ManifestError as exc:
                    e.status, e.detail = "error", str(exc)
        entries.append(e)
    key = lambda e: (0, SYNTHETIC_ORDER.index(e.world)) if e.world in SYNTHETIC_ORDER else (1, 0)
    return sorted(entries, key=key)


def _ensure_loaded(e: SettingEntry) -> bool:
    from ..datasets import ManifestError, load_setting

    if e.setting is None and e.status == "ok":
        try:
            e.setting = load_setting(e.run_manifest)
        except ManifestError as exc:
            e.status, e.detail = "error", str(exc)
    return e.status == "ok"


def context(profile: str = "fixture", models: str = "offline", build: bool = True,
            methods: Sequence[str] = RUN_METHODS, root: Path | None = None, progress: bool = True,
            validate: bool = False) -> PaperContext:
    """Locate (and with ``build``, create or resume) every run of a notebook profile.

    ``fixture``: the synthetic fixture suite, runs cached in ``build/fixture/runs``
    (built when missing, reused when current). ``paper-default``: the paper suite
    in ``build/runs`` (what ``cerpe paper`` builds). ``validate`` loads every
    enabled setting even when its runs are cached (surfaces data errors).
    """
    root = Path(root or ROOT)
    if models not in MODELS:
        raise PaperError(f"unknown models {models!r}; known: {', '.join(MODELS)}")
    lay = _layout(profile, models, root)
    suite = "fixture" if profile == "fixture" else "paper-default"
    ctx = PaperContext(profile, suite, models, lay["runs"], lay["figures"], lay["tables"], lay["notebooks"])
    ctx.settings = discover_settings(profile, suite, root / "datasets_manifest", lay["manifests"], load=validate)
    for e in ctx.settings:
        if e.status != "ok":
            continue
        for m in methods:
            out = ctx.runs_root / e.name / m
            ctx.run_dirs[(e.name, m)] = out
            if not build or run_is_current(out, e.run_manifest, m, sets=ctx.sets_of(m)):
                continue
            try:
                if not _ensure_loaded(e):
                    break
                run_method(e.run_manifest, m, out, sets=ctx.sets_of(m), overwrite=True, progress=progress,
                           setting=e.setting)
            except CerpeError as exc:
                msg = f"{e.name}/{m}: {exc}"
                log.error(msg)
                ctx.errors.append(msg)
                ctx.run_dirs.pop((e.name, m))
        if e.status != "ok":
            log.error("setting %s: %s", e.name, e.detail)
            ctx.errors.append(f"{e.name}: {e.detail}")
            for m in methods:
                ctx.run_dirs.pop((e.name, m), None)
    return ctx


def frames(ctx: PaperContext, setting: str | None = None) -> pd.DataFrame:
    """Evaluated frames (``evaluate.frame_errors``) of every run of ``ctx`` (or one setting)."""
    dirs = [p for (s, m), p in ctx.run_dirs.items() if setting is None or s == setting]
    if not dirs:
        raise EvalError(f"no finished runs for {setting or 'any setting'} under {ctx.runs_root}")
    f, _ = evaluate_runs(dirs)
    return f


# --------------------------------------------------------------------------- figure data
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
    if not _ensure_loaded(entry):
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
    return gate_tau(json.loads((run_dir / "run.json").read_text()))


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


# --------------------------------------------------------------------------- notebooks
def _inputs_fingerprint(ctx: PaperContext, params: dict) -> str:
    h = hashlib.sha256(json.dumps(params, sort_keys=True).encode())
    for key, p in [*sorted(ctx.run_dirs.items()), *((str(q), q) for q in sorted(ctx.extra_runs))]:
        h.update(str(key).encode())
        for f in sorted(p.glob("*/DONE.json")) + [p / "run.json"]:
            if f.exists():
                h.update(f.read_bytes())
    for e in ctx.settings:
        h.update(f"{e.name}:{e.status}:{e.detail}".encode())
    code = [ROOT / "cerpe" / "plotting.py", ROOT / "cerpe" / "pipeline" / "evaluate.py",
            ROOT / "cerpe" / "pipeline" / "paper.py", ROOT / "cerpe" / "pipeline" / "table1.py",
            ROOT / "cerpe" / "pipeline" / "message_loss.py", ROOT / "cerpe" / "pipeline" / "pareto.py"] + [
                ROOT / "notebooks" / f"{n}.ipynb" for n in NOTEBOOKS]
    for f in code:
        if f.exists():
            h.update(f.read_bytes())
    return h.hexdigest()[:20]


def expected_outputs(ctx: PaperContext) -> list[Path]:
    out = [ctx.tables_dir / t for t in EXPECTED_TABLES + NOTEBOOK_TABLES]
    for stem in EXPECTED_FIGURES:
        out += [ctx.figures_dir / f"{stem}.png", ctx.figures_dir / f"{stem}.pdf"]
    for e in ctx.ok_settings:
        out += [ctx.figures_dir / f"qualitative_{e.name}.png"]
    return out


def run_notebooks(ctx: PaperContext, force: bool = False) -> bool:
    """Execute the notebooks with papermill unless inputs and outputs are unchanged. Returns True if run."""
    params = {"PROFILE": ctx.profile, "MODELS": ctx.models}
    fp = _inputs_fingerprint(ctx, params)
    stamp = ctx.notebooks_dir / "inputs.json"
    if not force and stamp.exists() and all(p.exists() for p in expected_outputs(ctx)):
        try:
            if json.loads(stamp.read_text()).get("fingerprint") == fp:
                log.info("notebooks: inputs unchanged and outputs present; not executed again")
                return False
        except json.JSONDecodeError:
            pass
    import papermill as pm

    ctx.notebooks_dir.mkdir(parents=True, exist_ok=True)
    for nb in NOTEBOOKS:
        src = ROOT / "notebooks" / f"{nb}.ipynb"
        dst = ctx.notebooks_dir / f"{nb}.ipynb"
        t0 = time.perf_counter()
        try:
            pm.execute_notebook(str(src), str(dst), parameters=params, cwd=str(ROOT / "notebooks"),
                                progress_bar=False, kernel_name="python3")
        except Exception as exc:  # papermill wraps the cell error; name the notebook and the error
            why = (f"{getattr(exc, 'ename', '')}: {getattr(exc, 'evalue', '')}" if hasattr(exc, "ename")
                   else next((ln for ln in str(exc).splitlines() if ln.strip()), type(exc).__name__))
            raise PaperError(f"notebook {src.name} failed (executed copy: {dst}): {why[:300]}") from None
        log.info("notebook %s: %.1f s", nb, time.perf_counter() - t0)
    atomic_write_json(stamp, {"fingerprint": fp, "params": params})
    return True


def build_paper(models: str = "offline", suite: str = "paper-default", force_notebooks: bool = False,
                progress: bool = True, jobs: int = 2) -> PaperContext:
    """Every run, then the notebooks. With ``jobs`` > 1 (paper-default only) the runs go to that many
    worker processes (:mod:`cerpe.pipeline.schedule`); the results are the same as with one."""
    nb_profile = "fixture" if suite == "fixture" else "paper-default"
    if models == "paper":  # one error listing what is missing, before any work
        from ..backbones.paper_profile import require_paper

        require_paper()
    pool = nb_profile != "fixture" and int(jobs) > 1
    if pool:  # the synthetic worlds render side by side (an error surfaces when context loads it below)
        from .schedule import Job, load_job, run_jobs

        lay = _layout(nb_profile, models, ROOT)
        synth = [e for e in discover_settings(nb_profile, nb_profile, ROOT / "datasets_manifest", lay["manifests"],
                                              load=False) if e.world and e.status == "ok"]
        run_jobs([Job(f"{e.name}/render", load_job, (e.run_manifest,)) for e in synth], int(jobs), progress)
    ctx = context(nb_profile, models=models, build=not pool, progress=progress, validate=True)
    t0 = time.perf_counter()
    if pool:
        from .schedule import paper_jobs

        for job, err in run_jobs(paper_jobs(ctx, run_is_current), workers=int(jobs), progress=progress):
            msg = f"{job.name}: {err}"
            log.error(msg)
            ctx.errors.append(msg)
            for key in job.outputs:
                ctx.run_dirs.pop(key, None)
        log.info("runs on %d worker processes: %.1f s", int(jobs), time.perf_counter() - t0)
    from .pareto import context_runs  # the Pareto settings on a few encounters (notebook 07 reads them)

    runs, errors = context_runs(ctx, build=not pool, progress=progress)
    ctx.extra_runs = sorted({r.path for r in runs if r.path.name.startswith("pareto-")})
    ctx.errors += errors
    log.info("Pareto settings: %.1f s", time.perf_counter() - t0)
    run_notebooks(ctx, force=force_notebooks)
    return ctx


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--models", default="offline", choices=MODELS,
                   help="backbone.models of every CERPE run: offline (the stand-ins that run here) or paper "
                        "(VGGT + SALAD/DINOv2 + Metric3Dv2, needs your weights: docs/PAPER_MODELS.md)")
    p.add_argument("--suite", default="paper-default", choices=("paper-default", "fixture"),
                   help="synthetic suite size; fixture writes to build/fixture/ only")
    p.add_argument("--force-notebooks", action="store_true", help="execute the notebooks even if nothing changed")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--jobs", type=int, default=2, metavar="N",
                   help="worker processes for the runs of --suite paper-default (default 2, for 2 cores; "
                        "1: every run in this process with per-encounter progress bars); the tables are "
                        "the same for any N")


def main(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    if args.jobs < 1:
        print(f"cerpe paper: error: --jobs {args.jobs}: at least 1", file=sys.stderr)
        return 2
    ctx = build_paper(args.models, args.suite, args.force_notebooks, progress=not args.no_progress, jobs=args.jobs)
    print(f"tables:    {ctx.tables_dir}")
    print(f"figures:   {ctx.figures_dir}")
    print(f"notebooks: {ctx.notebooks_dir}")
    print(f"runs:      {ctx.runs_root}")
    for e in ctx.settings:
        print(f"  setting {e.name}: {e.status}{' (' + e.detail + ')' if e.detail else ''}")
    for m, why in UNAVAILABLE.items():
        print(f"  method {m}: not available offline ({why})")
    print(f"done in {time.perf_counter() - t0:.1f} s")
    if ctx.errors or any(e.status == "error" for e in ctx.settings):
        for msg in ctx.errors:
            print(f"cerpe paper: error: {msg}", file=sys.stderr)
        return 1
    return 0
