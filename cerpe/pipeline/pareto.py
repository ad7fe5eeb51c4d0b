"""Bytes against accuracy: the Pareto table and the runs behind it.

Schemes, each a point of bytes per robot per step against e_rot / e_pos:

* ``paper``: the paper's protocol (gate, then an image request every time it opens):
  the ``cerpe`` runs Table I already made, read on the same encounters, never re-run;
* :data:`PARETO_PRESETS`: CERPE at other named presets (:data:`cerpe.method_config.PRESETS`),
  run on a small subset of each setting's encounters (``n_encounters`` per setting, the first
  ones) to keep ``make paper`` cheap: ``always`` (an image to every peer at every step: the
  always-send reference) and ours at several settings;
* the per-frame baselines (images every step, as always-send) where their runs exist.

Runs of the settings live beside the method runs, ``<runs>/<setting>/pareto-<name>/``,
cached and resumed like every run (a changed preset is a new run). Plain functions;
the figure is :func:`cerpe.plotting.pareto_figure`, the notebook ``07_pareto``.
"""
from __future__ import annotations

import dataclasses
import fnmatch
import logging
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import pandas as pd

from ..atomicio import read_json
from ..errors import CerpeError
from ..runfolder.current import run_is_current
from ..runfolder.read import load_run
from .evaluate import frame_errors, summarise

log = logging.getLogger(__name__)

# The presets of the Pareto figure besides the paper's (each costs about a minute of `make paper`; at most 4)
PARETO_PRESETS: tuple[str, ...] = ("always", "pays", "pays-compressed", "lean")
PARETO_LABELS: dict[str, str] = {
    "paper": "paper's protocol (gate, request every time)",
    "always": "always send (image to every peer, every step)",
    "pays": "ours: request when it pays",
    "pays-compressed": "ours + compressed messages (PCA int8 descriptor, WebP 75)",
    "lean": "ours, lean: + back-off from gates whose images do not place, recheck, grey WebP 75",
    "aliked-lightglue": "per-frame ALIKED+LightGlue (images every step)",
    "sift-ransac": "per-frame SIFT+RANSAC (images every step)",
}
N_ENCOUNTERS = 1  # per setting, in `make paper` (cost); the development script runs them all
BASELINES: tuple[str, ...] = ("aliked-lightglue", "sift-ransac")


class ParetoError(CerpeError, ValueError):
    """The Pareto table cannot be built (no runs, an unknown setting name)."""


@dataclasses.dataclass(frozen=True)
class SchemeRun:
    """One scheme on one setting: its run folder and the encounters that count (None: all)."""

    setting: str
    scheme: str
    path: Path
    encounters: tuple[str, ...] | None = None


def run_dir(runs_root: Path, setting: str, scheme: str) -> Path:
    return Path(runs_root) / setting / f"pareto-{scheme}"


def scheme_runs(sets: Sequence[tuple[str, Path, Any]], runs_root: Path, *, knob_sets: Mapping | None = None,
                schemes: Sequence[str] | None = None, n_encounters: int | None = N_ENCOUNTERS,
                build: bool = True, progress: bool = True,
                only: Sequence[str] | None = None) -> tuple[list[SchemeRun], list[str]]:
    """Run (or find) every Pareto setting on the first ``n_encounters`` encounters of each set.

    Args:
        sets: ``(name, manifest, Setting or None)``; a None setting is loaded when a run is needed.
        knob_sets: dotted knobs every run takes besides its preset (``cerpe paper --set``).
        schemes: preset names (default :data:`PARETO_PRESETS`).
        n_encounters: encounters per set (None: all).
        only: keep the encounters whose name matches one of these shell patterns (before
            ``n_encounters``; a set none of whose encounters match is left out).
        build: False only locates finished current runs (notebooks of ``make paper``).

    Returns:
        ``(runs, errors)``: one :class:`SchemeRun` per finished (set, scheme); an error
        line per run that failed (the others go on).
    """
    from .run import run_method
    from .setting import load_manifest_setting

    schemes = PARETO_PRESETS if schemes is None else tuple(schemes)
    out, errors = [], []
    for name, manifest, setting in sets:
        manifest = Path(manifest)
        for scheme in schemes:
            path = run_dir(runs_root, name, scheme)
            try:
                if setting is None and (build or not (path / "run.json").exists()):
                    setting = load_manifest_setting(manifest)
                encs = (list(setting.encounters) if setting is not None else None)
                if encs is None:  # not building: the run says which encounters it ran
                    wanted = read_json(path / "run.json", "run.json")["config"]["encounters"]
                else:
                    if only:
                        encs = [e for e in encs if any(fnmatch.fnmatchcase(e.name, q) for q in only)]
                        if not encs:
                            continue
                    encs = encs if n_encounters is None else encs[:int(n_encounters)]
                    wanted = [e.name for e in encs]
                if not run_is_current(path, manifest, "cerpe", scheme, knob_sets, wanted):
                    if not build:
                        errors.append(f"{name}/pareto-{scheme}: no current run under {path}")
                        continue
                    sub = dataclasses.replace(setting, encounters=encs)
                    run_method(manifest, "cerpe", path, preset=scheme, sets=knob_sets, overwrite=True,
                               progress=progress, setting=sub)
                out.append(SchemeRun(name, scheme, path))
            except (CerpeError, KeyError) as exc:
                errors.append(f"{name}/pareto-{scheme}: {exc}")
                log.error("%s/pareto-%s: %s", name, scheme, exc)
    return out, errors


def _loaded(r: SchemeRun) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    run = load_run(r.path)
    S, R = run.steps, run.robots
    if r.encounters is not None:
        S, R = S[S["encounter"].isin(r.encounters)], R[R["encounter"].isin(r.encounters)]
    if not len(S):
        raise ParetoError(f"{r.path}: none of the encounters {list(r.encounters or [])}")
    S = S.reset_index(drop=True)
    return frame_errors(S, run.metric_scale, run.every), S, R


def pareto_table(runs: Sequence[SchemeRun]) -> pd.DataFrame:
    """One row per (setting, scheme) and per scheme over the settings that have every scheme (``"all"``).

    Columns: ``bytes_per_robot_step`` (all messages), ``descriptor_bytes``, ``image_bytes``
    (requests + replies) per robot per step, ``vs_always`` (bytes over the ``always``
    scheme's on the same encounters), ``image_vs_paper`` (image bytes over the paper
    protocol's), ``e_rot_rad``, ``e_rot_median_rad``, ``e_pos_m`` (predicted scale;
    NaN for up-to-scale methods), ``e_pos_gt_scale_m``, ``success_pct``,
    ``success_after_covis_pct``, ``n_frames`` (evaluated), ``requests`` (image requests: pair rows
    with bytes, every step), ``requests_skipped`` (open gates the policy did not ask).
    """
    if not runs:
        raise ParetoError("no Pareto runs to tabulate")
    F, S, R = [], [], []
    for r in runs:
        for acc, df in zip((F, S, R), _loaded(r)):
            acc.append(df.assign(setting=r.setting, scheme=r.scheme))
    frames, steps, robots = (pd.concat(x, ignore_index=True) for x in (F, S, R))
    # "all" pools the settings that have every scheme but the baselines (its rows cover the same frames)
    have, need = robots.groupby("setting")["scheme"].agg(set), set(robots["scheme"]) - set(BASELINES)
    common = [s for s, v in have.items() if need <= v]
    rows = []
    for setting in [*sorted(frames["setting"].unique()), "all"]:
        pick = (lambda df: df[df["setting"].isin(common)]) if setting == "all" else \
            (lambda df, s=setting: df[df["setting"] == s])
        fs, rs, ss = pick(frames), pick(robots), pick(steps)
        summ = summarise(fs, ["scheme"]).set_index("scheme")
        for scheme, g in rs.groupby("scheme", sort=False):
            if scheme not in summ.index:
                continue
            s = summ.loc[scheme]
            col = lambda c: g[c].astype(float) if c in g else pd.Series(0.0, index=g.index)
            fr = ss[ss["scheme"] == scheme]
            rows.append({
                "setting": setting, "scheme": scheme, "label": PARETO_LABELS.get(scheme, scheme),
                "bytes_per_robot_step": float(g["bytes_total"].mean()),
                "descriptor_bytes": float(col("bytes_descriptor").mean()),
                "image_bytes": float((col("bytes_request") + col("bytes_reply")).mean()),
                "e_rot_rad": s["e_rot_rad"], "e_rot_median_rad": s["e_rot_median_rad"], "e_pos_m": s["e_pos_m"],
                "e_pos_gt_scale_m": s["e_pos_gt_scale_m"], "success_pct": s["success_pct"],
                "success_after_covis_pct": s["success_after_covis_pct"], "n_frames": int(s["n_frames"]),
                "requests": int((fr["bytes_pair"] > 0).sum()) if "bytes_pair" in fr else 0,
                "requests_skipped": (int(fr["request_skipped"].fillna(False).astype(bool).sum())
                                     if "request_skipped" in fr else 0),  # runs of older code lack it
            })
    t = pd.DataFrame(rows)
    for col, ref in (("vs_always", "always"), ("image_vs_paper", "paper")):
        base = t[t["scheme"] == ref].set_index("setting")["bytes_per_robot_step" if ref == "always"
                                                            else "image_bytes"]
        num = t["bytes_per_robot_step"] if ref == "always" else t["image_bytes"]
        t[col] = num / t["setting"].map(base).replace(0, np.nan)
    order = {k: i for i, k in enumerate(["always", "paper", *PARETO_PRESETS, *BASELINES])}
    t["_o"] = t["scheme"].map(lambda s: order.get(s, len(order)))
    t = t.sort_values(["setting", "_o"], key=lambda c: c if c.name == "_o" else c.map(lambda v: (v == "all", v)))
    return t.drop(columns="_o").reset_index(drop=True)


def breakdown(runs: Sequence[SchemeRun]) -> pd.DataFrame:
    """Where a scheme's bytes go and where its e_rot comes from, one row per (setting, scheme).

    Columns: bytes per robot per step by message kind (``descriptor``, ``pose``, ``request``,
    ``reply``: the run's ``bytes_<kind>``), ``requests`` (pair rows with image bytes),
    ``reply_bytes`` (mean bytes of one request + reply), ``placed`` (fraction of requests
    that gave this step's estimate directly), and over the evaluated successful frames:
    ``n_direct`` / ``e_rot_direct_rad``, ``n_propagated`` / ``e_rot_propagated_rad`` and
    ``anchor_age`` (mean steps since the anchor of a propagated estimate).
    """
    rows = []
    for r in runs:
        frames, steps, robots = _loaded(r)
        req = steps[steps["bytes_pair"] > 0] if "bytes_pair" in steps else steps.iloc[:0]
        ok = frames[frames["success"]]
        row: dict[str, Any] = {"setting": r.setting, "scheme": r.scheme}
        for kind in ("descriptor", "pose", "request", "reply"):
            row[kind] = float(robots[f"bytes_{kind}"].mean()) if f"bytes_{kind}" in robots else 0.0
        row.update(requests=len(req), reply_bytes=float(req["bytes_pair"].mean()) if len(req) else float("nan"),
                   placed=float((req["source"] == "direct").mean()) if len(req) else float("nan"))
        for src in ("direct", "propagated"):
            g = ok[ok["source"] == src]
            row[f"n_{src}"], row[f"e_rot_{src}_rad"] = len(g), float(g["e_rot_rad"].mean()) if len(g) else float("nan")
        prop = ok[ok["source"] == "propagated"]
        row["anchor_age"] = float((prop["step"] - prop["anchor_step"]).mean()) if len(prop) else float("nan")
        rows.append(row)
    return pd.DataFrame(rows)


def format_markdown(table: pd.DataFrame, setting: str = "all") -> str:
    """The rows of one setting as a Markdown table (what the issue's check reads)."""
    t = table[table["setting"] == setting]
    cols = ["label", "bytes_per_robot_step", "image_bytes", "vs_always", "e_rot_rad", "e_pos_m", "success_pct",
            "success_after_covis_pct", "requests", "requests_skipped", "n_frames"]
    head = "| " + " | ".join(cols) + " |\n|" + "---|" * len(cols) + "\n"
    fmt = lambda v: (f"{v:.4g}" if isinstance(v, (float, np.floating)) and np.isfinite(v)
                     else ("n/a" if isinstance(v, (float, np.floating)) else str(v)))
    return head + "".join("| " + " | ".join(fmt(r[c]) for c in cols) + " |\n" for _, r in t.iterrows())


def check(table: pd.DataFrame, scheme: str = "pays", setting: str = "all") -> dict[str, float]:
    """The issue's check for one scheme: bytes over always-send (target <= 0.10), e_rot and
    success over the paper protocol's (targets <= 1.1 and >= 0.98)."""
    t = table[table["setting"] == setting].set_index("scheme")
    if not {scheme, "paper", "always"} <= set(t.index):
        raise ParetoError(f"check: {setting!r} lacks one of {scheme!r}, 'paper', 'always'")
    s, p = t.loc[scheme], t.loc["paper"]
    return {"bytes_vs_always": float(s["vs_always"]), "image_bytes_vs_paper": float(s["image_vs_paper"]),
            "e_rot_vs_paper": float(s["e_rot_rad"] / p["e_rot_rad"]),
            "success_vs_paper": float(s["success_pct"] / p["success_pct"]) if p["success_pct"] else float("nan")}


# --------------------------------------------------------------------------- make paper
def context_runs(ctx: Any, build: bool = False, progress: bool = True,
                 n_encounters: int | None = N_ENCOUNTERS) -> tuple[list[SchemeRun], list[str]]:
    """Every scheme of a :class:`~cerpe.pipeline.paper.PaperContext`: the Pareto settings run (with
    ``build``) or found on its synthetic settings' first encounters, the paper protocol and the
    baselines read from the context's runs on the same encounters."""
    sets = [(e.name, e.run_manifest, e.setting) for e in ctx.ok_settings if e.world]  # synthetic only
    runs, errors = scheme_runs(sets, ctx.runs_root, knob_sets=ctx.sets, n_encounters=n_encounters, build=build,
                               progress=progress)
    for r in list(runs):
        if r.scheme != "always":
            continue
        encs = tuple(read_json(r.path / "run.json", "run.json")["config"]["encounters"])
        for method, scheme in (("cerpe", "paper"), *((b, b) for b in BASELINES)):
            p = ctx.run_dirs.get((r.setting, method))
            if p is not None and p.is_dir():
                runs.append(SchemeRun(r.setting, scheme, p, encs))
    return runs, errors
