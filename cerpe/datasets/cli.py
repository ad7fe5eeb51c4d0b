"""Validate dataset manifests, load them and summarise them; list every problem at once.

For each MANIFEST: the schema is validated. An enabled manifest is then loaded
with its adapter (trajectories, intrinsics, synchronisation) and every image and
depth file is decoded and compared with the intrinsics (`cerpe run` makes the
same checks on a few frames per robot). A summary follows:
robots, frames, encounters, ordered pairs, stamp residuals, ground-truth
overlap (mean, fraction of steps >= 0.2) and the relative viewing-angle range.
Counted degradations (frames without ground truth, dropped unsynchronised
frames, missing depth, depth maps without a valid pixel) are listed, and warnings
(a median depth that suggests wrong depth_units_per_m); they are not errors.

Exit status: 0 when every manifest is fine, 2 when any problem was found.

Examples:
  cerpe check datasets_manifest/*.yaml
  cerpe check my-robots.yaml --frames 20     # decode only 20 frames per robot
"""
from __future__ import annotations

import argparse
import math
import sys

from . import LoadReport, ManifestError, disabled_reason, load_manifest, load_setting
from .summary import summarise


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("manifests", nargs="+", metavar="MANIFEST", help="dataset manifest YAML file(s)")
    parser.add_argument("--frames", type=_at_least_one, default=None, metavar="N",
                        help="decode at most N evenly spaced frames per robot and encounter (default: all)")
    parser.add_argument("--no-verify", action="store_true",
                        help="do not decode image/depth files (ids, intrinsics and depth file headers are still checked)")
    parser.add_argument("--per-encounter", action="store_true", help="also print one line per encounter")


def _at_least_one(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {n} (it would check no frame)")
    return n


def _fmt(v: float, spec: str = ".3f", unit: str = "") -> str:
    return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:{spec}}{unit}"


def depth_source_problem(path: str, manifest) -> str:
    """The manifest's depth source built with its options ("" when it builds): a misspelt or bad
    option is a problem naming the file and field. ``metric3d`` is not built here (it loads weights)."""
    from ..backbones.depth import DepthSourceError, build_depth_source

    if manifest.metric_depth == "metric3d":
        return ""
    try:
        build_depth_source(manifest.metric_depth, manifest.metric_depth_options)
    except DepthSourceError as exc:
        return f"{path}: metric_depth_options: {exc}"
    return ""


def check_one(path: str, frames: int | None, verify: bool, per_encounter: bool, out=None) -> list[str]:
    """Check one manifest, print its summary to ``out`` (stdout); returns the problems as lines."""
    out = out if out is not None else sys.stdout
    try:
        manifest = load_manifest(path)
    except ManifestError as exc:
        return [str(p) for p in exc.problems]
    bad_depth = depth_source_problem(path, manifest)
    if bad_depth:
        return [bad_depth]
    if not manifest.enabled:
        print(f"{path}: {manifest.name} ({manifest.adapter}): {disabled_reason(manifest)}; schema OK", file=out)
        return []
    report = LoadReport()
    try:  # the checks a run makes, on every frame (or --frames N)
        setting = load_setting(manifest, report, frames=frames if verify else 0, progress=True, log=False)
    except ManifestError as exc:
        return [str(p) for p in exc.problems]
    s = summarise(setting)
    print(f"{path}: {s['setting']} ({manifest.adapter}, metric depth: {setting.metric_depth})", file=out)
    print(f"  encounters {s['encounters']}  robots {s['robots']}  frames {s['frames']}  steps {s['steps']}  "
          f"ordered pairs {s['pairs']} (with ground truth {s['pairs_with_gt']})", file=out)
    line = f"  stamp residual (stamp sync) max {_fmt(s['sync_max_abs_s'] * 1e3, '.1f', ' ms')}"
    if not math.isnan(s["index_sync_max_offset_s"]):
        line += f"; stamp offset between index-synced robots max {s['index_sync_max_offset_s']:.3f} s"
    print(line, file=out)
    print(f"  overlap: mean {_fmt(s['overlap_mean'])}, steps with overlap >= 0.2: "
          f"{_fmt(s['overlap_frac_ge_0_2'] * 100, '.1f', ' %')}", file=out)
    print(f"  viewing angle range {_fmt(s['view_angle_min_deg'], '.1f')} .. {_fmt(s['view_angle_max_deg'], '.1f', ' deg')}",
          file=out)
    for (enc, reason), n in sorted(report.counts.items()):
        print(f"  counted: {enc}: {reason}: {n}", file=out)
    for w in report.warnings:
        print(f"  warning: {w}", file=out)
    if per_encounter:
        for r in s["per_encounter"]:
            print(f"    {r['encounter']}: robots {r['robots']} steps {r['steps']} pairs {r['pairs']} "
                  f"gt {r['pairs_with_gt']} overlap {_fmt(r['overlap_mean'])} "
                  f"max angle {_fmt(r['view_angle_max_deg'], '.1f')}", file=out)
    return []


def main(args: argparse.Namespace) -> int:
    all_problems: list[str] = []
    for path in args.manifests:
        all_problems += check_one(path, args.frames, not args.no_verify, args.per_encounter)
    if all_problems:
        print(f"cerpe check: {len(all_problems)} problem(s):", file=sys.stderr)
        for p in all_problems:
            print(f"  - {p}", file=sys.stderr)
        return 2
    print("cerpe check: OK")
    return 0
