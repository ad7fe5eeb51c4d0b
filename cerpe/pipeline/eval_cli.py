"""``cerpe eval``: the paper's metrics of run folders, printed as a table.

Usage: ``cerpe eval RUNDIR [RUNDIR ...] [--by encounter|setting] [--csv OUT.csv]``

The metrics and how frames are counted: :mod:`cerpe.pipeline.evaluate`. The folders of the
robots of one ``cerpe online`` team, given together, are evaluated as the team.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd

from ..atomicio import atomic_write_text
from .evaluate import COVIS_POSITIVE, RIGHT_ROT_RAD, evaluate


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
