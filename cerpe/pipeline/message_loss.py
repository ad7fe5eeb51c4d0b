"""The message-loss sweep: CERPE's results against the fraction of frames lost.

One pipeline step, :func:`main` ``(conf, paths) -> Path``: for each loss probability
and loss seed, ``cerpe run --loss P --loss-seed N`` on the first ``encounters``
encounters of one setting (a small subset: the sweep must stay cheap inside
``make paper``), each a normal run folder (cached, resumed, fingerprinted); the
lossless point reuses the setting's full lossless run when one is given and current
(its frames of the same encounters). ``cerpe-wo-em`` costs nothing more: the methods of
one loss and seed run together (:func:`cerpe.pipeline.run.run_methods`), one pass per encounter. The summary
(one row per method and loss: success, success after co-visibility, e_rot, e_pos,
the degradations per robot-step, and the ratios to lossless the issue checks) is
written to ``summary.csv`` in the sweep folder and returned; the notebook
(``notebooks/06_message_loss.ipynb``) turns it into ``tables/message_loss.*`` and
the figure. A second call with nothing changed only checks the runs.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from ..atomicio import atomic_write_json, atomic_write_text, read_json
from ..config import merge_conf
from ..errors import CerpeError
from ..transport import LossSpec
from ..runfolder.current import run_is_current
from .evaluate import evaluate_runs, summarise
from .textfmt import md_table

log = logging.getLogger(__name__)

default_conf: dict[str, Any] = {
    "setting": "synthetic-indoor",   # the setting whose encounters are swept
    "encounters": 1,                 # its first N encounters
    "max_steps": 24,                 # their first steps only (None: all); CERPE is causal, so these are
                                     # the same steps of the full lossless run
    "losses": [0.0, 0.1, 0.3, 0.5],  # drop probability of every frame, per receiver
    "garble": 0.0,                   # probability that a frame that arrives is corrupted
    "loss_seeds": [1, 2],            # one run per seed and loss > 0; the frames of all seeds pooled
    "methods": ["cerpe", "cerpe-wo-em"],
    "models": "offline",             # backbone.models of the runs (offline | paper)
    "seed": 0,                       # the runs' seed (as the lossless run's)
}

#: degradations the sweep reports per robot-step (what was lost, and what the robots did about it)
COUNTED: tuple[str, ...] = ("msg:lost", "msg:garbled", "descriptor:missing", "descriptor:stale-used", "msg:request-retried", "msg:reply-missing",
                            "pose:stale",
                            "pose:bridged", "pose:bridged-next", "anchor:not-stored-pose-missing")
# the check at 30 % loss: success after co-visibility >= 95 % of lossless, e_rot <= 1.2 x
CHECK_LOSS, CHECK_SUCCESS, CHECK_EROT = 0.3, 0.95, 1.2


class MessageLossError(CerpeError, ValueError):
    """A sweep that cannot run (bad configuration, no such setting or encounters)."""


def run_dir(runs: Path, method: str, loss: float, seed: int) -> Path:
    """The sweep's run folder of one method, loss and loss seed."""
    return Path(runs) / f"{method}-loss{round(100 * loss):02d}-seed{int(seed)}"


def main(conf: dict | None, paths: dict, setting: Any = None, progress: bool = False) -> Path:
    """Run (or find) the sweep's runs and write their summary; returns ``paths["runs"]/summary.csv``.

    Args:
        conf: overrides of :data:`default_conf` (strict merge).
        paths: ``manifest`` (the setting's run manifest), ``runs`` (the sweep's folder),
            optionally ``lossless`` ({method: the setting's full lossless run folder},
            reused for loss 0 when current).
        setting: the loaded setting of ``manifest`` (loaded when a run must be made).
    """
    from .run import run_methods
    from .setting import load_manifest_setting

    c = merge_conf(default_conf, conf or {}, "message_loss")
    losses = sorted({float(p) for p in c["losses"]})
    if not losses or not all(0.0 <= p < 1.0 for p in losses):
        raise MessageLossError(f"message_loss.losses {c['losses']}: probabilities in [0, 1)")
    if int(c["encounters"]) < 1 or not c["loss_seeds"] or not c["methods"]:
        raise MessageLossError("message_loss: encounters >= 1, and at least one loss seed and method")
    max_steps = None if c["max_steps"] is None else int(c["max_steps"])
    if max_steps is not None and max_steps < 1:
        raise MessageLossError(f"message_loss.max_steps {max_steps}: >= 1 (or None: every step)")
    manifest, runs = Path(paths["manifest"]), Path(paths["runs"])
    lossless = {m: Path(p) for m, p in (paths.get("lossless") or {}).items()}
    sets = {} if c["models"] == "offline" else {"backbone.models": c["models"]}

    def sub_setting() -> Any:
        nonlocal setting
        if setting is None:
            setting = load_manifest_setting(manifest)
        if setting.name != c["setting"]:
            raise MessageLossError(f"{manifest}: setting {setting.name!r}, the sweep is of {c['setting']!r}")
        return dataclasses.replace(setting, encounters=[_first_steps(e, max_steps)
                                                        for e in setting.encounters[: int(c["encounters"])]])

    plan: list[tuple[str, float, int, Path]] = []  # (method, loss, loss seed, run folder)
    for p in losses:
        for s in (c["loss_seeds"] if p > 0 else [0]):
            stale: dict[str, Path] = {}
            for m in c["methods"]:
                reuse = lossless.get(m)
                if p == 0 and reuse is not None and run_is_current(reuse, manifest, m, sets=sets):
                    plan.append((m, p, -1, reuse))
                    continue
                out = run_dir(runs, m, p, s)
                if not run_is_current(out, manifest, m, sets=sets):
                    stale[m] = out
                plan.append((m, p, int(s), out))
            if stale:  # the cerpe methods of one loss and seed share each encounter's pass
                run_methods(manifest, stale, sets=sets, seed=int(c["seed"]), overwrite=True, progress=progress,
                            setting=sub_setting(), loss=LossSpec(p, float(c["garble"]) if p > 0 else 0.0, int(s)))
    summary = runs / "summary.csv"
    key = _fingerprint(c, plan)
    stamp = runs / "summary.json"
    if summary.is_file() and stamp.is_file() and read_json(stamp, "summary.json").get("fingerprint") == key:
        return summary
    table = summarise_sweep(plan, max_steps)
    atomic_write_text(summary, table.to_csv(index=False, float_format="%.6g"))
    atomic_write_json(stamp, {"fingerprint": key, "conf": c, "runs": [str(p) for *_, p in plan]})
    return summary


def _fingerprint(conf: dict, plan: list[tuple[str, float, int, Path]]) -> str:
    h = hashlib.sha256(json.dumps(conf, sort_keys=True).encode() + Path(__file__).read_bytes())  # code: columns
    for m, p, s, out in plan:
        h.update(f"{m}:{p}:{s}:{out}".encode())
        for f in [out / "run.json", *sorted(out.glob("*/DONE.json"))]:
            h.update(f.read_bytes())
    return h.hexdigest()[:20]


def _first_steps(enc: Any, n: int | None) -> Any:
    """``enc`` cut to its first ``n`` steps (unchanged when it has no more)."""
    if n is None or enc.n_steps <= n:
        return enc
    from ..scene import Encounter, RobotStream

    robots = [RobotStream(r.robot_id, r.intrinsics, r.stamps_s[:n], list(r.images[:n]), r.T_world_cam[:n],
                          None if r.depth is None else list(r.depth[:n]), r.depth_units_per_m,
                          list(r.frame_ids[:n])) for r in enc.robots]
    return Encounter(enc.name, robots, None if enc.overlap is None else enc.overlap[:n], dict(enc.meta))


def summarise_sweep(plan: list[tuple[str, float, int, Path]], max_steps: int | None = None) -> pd.DataFrame:
    """One row per (method, loss) over the sweep's encounters and steps, frames of all loss seeds pooled."""
    # the sweep's own runs name the encounters; a reused lossless run gives its frames of those
    encounters = {d.name for _, _, s, out in plan if s >= 0 for d in out.iterdir() if (d / "DONE.json").is_file()}
    frames, counts = [], []
    for m, p, s, out in plan:
        f, _ = evaluate_runs([out])
        f = f[f["encounter"].isin(encounters)] if encounters else f
        if max_steps is not None:  # a reused lossless run has every step
            f = f[f["step"] < max_steps]
        frames.append(f.assign(method=m, loss=p))
        robots = pd.concat([pd.read_csv(out / e / "robots.csv") for e in sorted(set(f["encounter"]))],
                           ignore_index=True)
        robots = robots if max_steps is None else robots[robots["step"] < max_steps]
        cell = robots["degradations"]
        degr = [str(v).split(";") if isinstance(v, str) else [] for v in cell]  # NaN: none that step
        row = {"method": m, "loss": p, "robot_steps": len(robots), "steps": int(robots["step"].max()) + 1}
        for name in COUNTED:
            row[name] = float(sum(d.count(name) for d in degr))
        counts.append(row)
    F = pd.concat(frames, ignore_index=True)
    out = summarise(F, ["method", "loss"])
    C = pd.DataFrame(counts)
    n_steps = int(C.pop("steps").max())
    C = C.groupby(["method", "loss"], as_index=False).sum()
    for name in COUNTED:  # per robot-step
        C[name] = C[name] / C["robot_steps"]
    out = out.merge(C.drop(columns="robot_steps"), on=["method", "loss"], how="left")
    out.insert(2, "encounters", len(set(F["encounter"])))
    out.insert(3, "steps", n_steps)
    base = out[out["loss"] == 0].set_index("method")
    ref_s = out["method"].map(base["success_after_covis_pct"]) if len(base) else np.nan
    ref_r = out["method"].map(base["e_rot_rad"]) if len(base) else np.nan
    out["success_after_covis_vs_lossless"] = out["success_after_covis_pct"] / ref_s
    out["e_rot_vs_lossless"] = out["e_rot_rad"] / ref_r
    return out


def check(summary: pd.DataFrame, method: str = "cerpe") -> dict[str, Any]:
    """The issue's check at 30 % loss: ``{"success_ratio", "e_rot_ratio", "passed"}`` (NaN/False without it)."""
    row = summary[(summary["method"] == method) & np.isclose(summary["loss"], CHECK_LOSS)]
    if row.empty:
        return {"success_ratio": float("nan"), "e_rot_ratio": float("nan"), "passed": False}
    s, r = float(row["success_after_covis_vs_lossless"].iloc[0]), float(row["e_rot_vs_lossless"].iloc[0])
    return {"success_ratio": s, "e_rot_ratio": r, "passed": bool(s >= CHECK_SUCCESS and r <= CHECK_EROT)}


def markdown(summary: pd.DataFrame) -> str:
    """The table as Markdown: percentages, radians, metres, ratios to lossless."""
    cols = {"method": "method", "loss": "loss", "success_pct": "success %",
            "success_after_covis_pct": "success after covis %", "e_rot_rad": "e_rot (rad)", "e_pos_m": "e_pos (m)",
            "success_after_covis_vs_lossless": "covis success / lossless", "e_rot_vs_lossless": "e_rot / lossless",
            "msg:lost": "lost / robot-step", "pose:bridged": "bridged / robot-step"}

    t = summary[list(cols)]
    rows = [[str(r["method"]), f"{100 * r['loss']:.0f} %"] + [f"{float(r[k]):.3f}" for k in list(cols)[2:]]
            for _, r in t.iterrows()]
    return md_table(list(cols.values()), rows)


def _entry(ctx: Any, setting: str) -> Any:
    """The context's entry of ``setting`` with data (MessageLossError when it has none)."""
    entry = next((e for e in ctx.settings if e.name == setting and e.status == "ok"), None)
    if entry is None:
        raise MessageLossError(f"message loss: setting {setting!r} has no data in this profile")
    return entry


def context_paths(ctx: Any, conf: dict | None = None) -> tuple[dict, dict]:
    """``(conf, paths)`` of :func:`main` for a paper context (``cerpe.pipeline.paper.context``):
    the sweep of its ``conf["setting"]`` (default synthetic-indoor) in ``<runs>/<setting>/message-loss/``,
    the loss-0 point from the context's lossless runs of that setting."""
    c = merge_conf(default_conf, conf or {}, "message_loss")
    entry = _entry(ctx, c["setting"])
    lossless = {m: ctx.run_dirs[(entry.name, m)] for m in c["methods"] if (entry.name, m) in ctx.run_dirs}
    return {**c, "models": ctx.models}, {"manifest": entry.run_manifest,
                                          "runs": ctx.runs_root / entry.name / "message-loss", "lossless": lossless}


def for_context(ctx: Any, conf: dict | None = None, progress: bool = False) -> Path:
    """:func:`main` on a paper context (see :func:`context_paths`)."""
    c, paths = context_paths(ctx, conf)
    return main(c, paths, setting=_entry(ctx, c["setting"]).setting, progress=progress)


def write_tables(summary: pd.DataFrame, tables_dir: Path) -> list[Path]:
    """``message_loss.csv`` and ``message_loss.md`` (with the issue's check below the table)."""
    tables_dir = Path(tables_dir)
    c = check(summary)
    note = (f"\nAt {CHECK_LOSS:.0%} loss, CERPE's success after co-visibility is {c['success_ratio']:.3f} x and "
            f"its e_rot {c['e_rot_ratio']:.3f} x the lossless values (target >= {CHECK_SUCCESS} and "
            f"<= {CHECK_EROT}: {'met' if c['passed'] else 'NOT met'}); "
            f"{int(summary['encounters'].max())} encounter(s) of the setting, their first "
            f"{int(summary['steps'].max())} steps.\n")
    out = [tables_dir / "message_loss.csv", tables_dir / "message_loss.md"]
    atomic_write_text(out[0], summary.to_csv(index=False, float_format="%.6g"))
    atomic_write_text(out[1], markdown(summary) + note)
    return out
