"""``cerpe eval``: the paper's metrics of run folders, printed as a table.

Usage: ``cerpe eval RUNDIR [RUNDIR ...] [--by encounter|setting] [--csv OUT.csv]``

The metrics and how frames are counted: :mod:`cerpe.pipeline.evaluate`. The folders of the
robots of one ``cerpe online`` team, given together, are evaluated as the team.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd

from collections import Counter

from ..atomicio import atomic_write_text
from ..reasons import DEGRADATIONS
from ..runfolder.read import load_run
from .evaluate import COVIS_POSITIVE, RIGHT_ROT_RAD, evaluate, evaluate_runs, summarise


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("rundirs", nargs="+", type=Path,
                   help="run folders written by `cerpe run` (or by `cerpe online`: the robots of one team together)")
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
    print("n_no_gt: evaluated frames without ground truth, left out. n_nonfinite: frames whose estimate in "
          "steps.csv is not finite, counted as failures.")
    if args.csv:
        atomic_write_text(args.csv, table.to_csv(index=False))
        print(f"written: {args.csv}")
    return 0


def run_summary(out: Path) -> str:
    """What a finished run did, in a few lines for the person who ran it: per setting the frames
    evaluated, the estimates (direct and propagated), success, right, the mean errors, and the
    degradations counted, by kind (:data:`cerpe.reasons.DEGRADATIONS`)."""
    frames, _ = evaluate_runs([out])
    run = load_run(out)
    t = summarise(frames, ["setting", "method"]).iloc[0]
    src = Counter(run.steps["source"].astype(str)) if "source" in run.steps else Counter()
    pos = f"e_pos {t['e_pos_m']:.3f} m" if pd.notna(t["e_pos_m"]) else f"e_pos {t['e_pos_gt_scale_m']:.3f} m at GT scale"
    lines = [f"{t['setting']} / {t['method']}: {int(t['n_frames'])} frames evaluated, {int(t['n_success'])} with an "
             f"estimate ({src.get('direct', 0)} direct, {src.get('propagated', 0)} propagated over all steps); "
             f"success {t['success_pct']:.1f} %, right {t['right_pct']:.1f} % (within {RIGHT_ROT_RAD:g} rad); "
             f"e_rot {t['e_rot_rad']:.3f} rad, {pos}"]
    counts: Counter = Counter()
    if "degradations" in run.robots:
        for cell in run.robots["degradations"].dropna().astype(str):
            counts.update(d for d in cell.split(";") if d)
    if counts:
        top = ", ".join(f"{k} {n}" for k, n in counts.most_common())
        lines.append(f"degradations (robot-steps): {top}")
        unknown = [k for k in counts if k not in DEGRADATIONS]
        if unknown:
            lines.append(f"  not in cerpe.reasons: {', '.join(unknown)}")
    else:
        lines.append("degradations: none")
    return "\n".join(lines)
