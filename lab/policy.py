"""Tune the image-request policy on development data (never on the paper-default suite).

Runs CERPE with the paper's protocol, always-send and the request policy at a few
thresholds on the development sets of ``cerpe dev`` (synthetic suites of seed >= 1
and the real ``datasets_manifest/dev-*.yaml`` sets whose data is present), every
encounter, and prints the Pareto table (``cerpe.pipeline.pareto``) per set and over
all, with each policy setting's bytes, e_rot and success against the paper's protocol and
always-send (:func:`cerpe.pipeline.pareto.check`).

    python -m lab.policy [--seeds 1] [--out build/dev] [--sets PATTERN ...] [--encounters PATTERN ...]

Runs are cached in ``<out>/runs/<set>/pareto-<name>/`` (resumed; a changed setting
is a new run); the table goes to ``<out>/policy.{csv,md}``.
"""
from __future__ import annotations

import argparse
import fnmatch
import sys
from pathlib import Path

from cerpe.algorithm.config import COMPRESSED_MESSAGES, LEAN, LEAN_V1_POLICY
from cerpe.atomicio import atomic_write_text
from cerpe.pipeline import dev, pareto

ROOT = Path(__file__).resolve().parents[1]
LEAN_V1 = {**LEAN, "request_policy": LEAN_V1_POLICY}  # LEAN before the recheck
# name -> CerpeConfig overrides; "paper" and "always" are the references of the check
GRID: dict[str, dict] = {
    "paper": {"request_policy": {"mode": "gate"}},
    "always": {"request_policy": {"mode": "always"}},
    "pays": {"request_policy": {"mode": "pays"}},  # PolicyConfig's defaults
    "pays-tight": {"request_policy": {"mode": "pays", "max_sigma_rot_rad": 0.03, "max_sigma_pos_m": 0.15,
                                      "max_steps": 15}},
    "pays-loose": {"request_policy": {"mode": "pays", "max_sigma_rot_rad": 0.1, "max_sigma_pos_m": 0.6,
                                      "max_steps": 60}},
    "pays-compressed": {"request_policy": {"mode": "pays"}, **COMPRESSED_MESSAGES},
    "pc-s75": {"request_policy": {"mode": "pays"}, **COMPRESSED_MESSAGES, "reply_scale": 0.75},
    "pc-s50": {"request_policy": {"mode": "pays"}, **COMPRESSED_MESSAGES, "reply_scale": 0.5},
    "pc-q50": {"request_policy": {"mode": "pays"}, **COMPRESSED_MESSAGES, "reply_quality": 50},
    "gate-compressed": {"request_policy": {"mode": "gate"}, **COMPRESSED_MESSAGES},
    "pays-int8": {"request_policy": {"mode": "pays"}, "descriptor_codec": "pca-int8"},
    "pays-webp": {"request_policy": {"mode": "pays"}, "reply_codec": "webp", "reply_quality": 75},
    "pi-j75": {"request_policy": {"mode": "pays"}, "descriptor_codec": "pca-int8", "jpeg_quality": 75},
    "pi-j50": {"request_policy": {"mode": "pays"}, "descriptor_codec": "pca-int8", "jpeg_quality": 50},
    "lean": LEAN,  # = "lean-pe-u2-rc-l1" below (LEAN since the commit that made it so); the entries below keep LEAN_V1
    "lean-v1": LEAN_V1,  # LEAN before: back-off every 3 steps after 3 misses, nothing else
    "lean-colour": {**LEAN_V1, "reply_codec": "webp"},  # LEAN before the grey replies
    "lean-g60": {**LEAN_V1, "reply_quality": 60},
    "lean-g90": {**LEAN_V1, "reply_quality": 90},  # is the grey-vs-colour placement loss the codec's quality?
    "lean-tight": {**LEAN_V1, "request_policy": {**LEAN_V1_POLICY, "max_sigma_rot_rad": 0.03, "max_sigma_pos_m": 0.15,
                                               "max_steps": 15}},  # spends the grey replies' bytes on fresher anchors
    "pi-backoff": {"request_policy": LEAN_V1_POLICY, "descriptor_codec": "pca-int8"},
    # success: only a pair with an anchor backs off (a pair without one loses the frames it does not ask
    # for), with a constant wait (ua) or one doubling per miss up to 12 steps (ua-grow: fewer bytes on anchored misses)
    "lean-ua": {**LEAN_V1, "request_policy": {**LEAN_V1_POLICY, "backoff_anchored_only": True}},
    "lean-ua-grow": {**LEAN_V1, "request_policy": {**LEAN_V1_POLICY, "backoff_anchored_only": True, "miss_backoff_growth": 2.0,
                                                 "miss_backoff_max_steps": 12}},
    # replace a doubtful anchor sooner instead of asking more often (pe: a pair whose candidates wait to verify does
    # not back off; u2: a pair without an anchor waits 2 steps, not 3; rc: ask again while the estimate that set the
    # anchor disagreed by > 0.03 rad with what verified it, up to 2 in a row; m: rotation sigma per metre travelled)
    "lean-pe": {**LEAN_V1, "request_policy": {**LEAN_V1_POLICY, "backoff_pending_exempt": True}},
    "lean-pe-u2": {**LEAN_V1, "request_policy": {**LEAN_V1_POLICY, "backoff_pending_exempt": True,
                                               "unanchored_backoff_steps": 2}},
    "lean-pe-rc": {**LEAN_V1, "request_policy": {**LEAN_V1_POLICY, "backoff_pending_exempt": True, "recheck_rot_rad": 0.03,
                                               "recheck_limit": 2}},
    "lean-ua-rc": {**LEAN_V1, "request_policy": {**LEAN_V1_POLICY, "backoff_anchored_only": True, "recheck_rot_rad": 0.03,
                                               "recheck_limit": 2}},
    "lean-pe-u2-rc": {**LEAN_V1, "request_policy": {**LEAN_V1_POLICY, "backoff_pending_exempt": True,
                                                  "unanchored_backoff_steps": 2, "recheck_rot_rad": 0.03,
                                                  "recheck_limit": 2}},
    "lean-pe-rc-m": {**LEAN_V1, "request_policy": {**LEAN_V1_POLICY, "backoff_pending_exempt": True, "recheck_rot_rad": 0.03,
                                                 "recheck_limit": 2, "rot_sigma_per_m": 0.005}},
    "lean-pe-u2-rc-m": {**LEAN_V1, "request_policy": {**LEAN_V1_POLICY, "backoff_pending_exempt": True,
                                                    "unanchored_backoff_steps": 2, "recheck_rot_rad": 0.03,
                                                    "recheck_limit": 2, "rot_sigma_per_m": 0.005}},
    "lean-pe-rc-m10": {**LEAN_V1, "request_policy": {**LEAN_V1_POLICY, "backoff_pending_exempt": True,
                                                   "recheck_rot_rad": 0.03, "recheck_limit": 2, "rot_sigma_per_m": 0.01}},
    # with rotation sigma per metre (m10: 0.01 rad/m; the cad robots drive 0.4-0.8 m per step), backing off after
    # 2 misses (b2), replies at WebP quality 60 (g60)
    "lean-pe-u2-rc-m10": {**LEAN_V1, "request_policy": {**LEAN_V1_POLICY, "backoff_pending_exempt": True,
                                                      "unanchored_backoff_steps": 2, "recheck_rot_rad": 0.03,
                                                      "recheck_limit": 2, "rot_sigma_per_m": 0.01}},
    "lean-pe-u2-rc-b2": {**LEAN_V1, "request_policy": {**LEAN_V1_POLICY, "miss_limit": 2, "backoff_pending_exempt": True,
                                                     "unanchored_backoff_steps": 2, "recheck_rot_rad": 0.03,
                                                     "recheck_limit": 2}},
    "lean-pe-u2-rc-m10-b2": {**LEAN_V1, "request_policy": {**LEAN_V1_POLICY, "miss_limit": 2, "backoff_pending_exempt": True,
                                                         "unanchored_backoff_steps": 2, "recheck_rot_rad": 0.03,
                                                         "recheck_limit": 2, "rot_sigma_per_m": 0.01}},
    # fewer rechecks for margin on bytes: a looser threshold (rc04: 0.04 rad) or one recheck at most (l1)
    "lean-pe-u2-rc04": {**LEAN_V1, "request_policy": {**LEAN_V1_POLICY, "backoff_pending_exempt": True,
                                                    "unanchored_backoff_steps": 2, "recheck_rot_rad": 0.04,
                                                    "recheck_limit": 2}},
    "lean-pe-u2-rc-l1": {**LEAN_V1, "request_policy": {**LEAN_V1_POLICY, "backoff_pending_exempt": True,
                                                     "unanchored_backoff_steps": 2, "recheck_rot_rad": 0.03,
                                                     "recheck_limit": 1}},
    "lean-pe-u2-rc-l1-b2": {**LEAN_V1, "request_policy": {**LEAN_V1_POLICY, "miss_limit": 2, "backoff_pending_exempt": True,
                                                        "unanchored_backoff_steps": 2, "recheck_rot_rad": 0.03,
                                                        "recheck_limit": 1}},
    "gate-s50": {"request_policy": {"mode": "gate"}, **COMPRESSED_MESSAGES, "reply_scale": 0.5},
    "pc-s50-tight": {"request_policy": {"mode": "pays", "max_sigma_rot_rad": 0.025, "max_sigma_pos_m": 0.15,
                                        "max_steps": 10}, **COMPRESSED_MESSAGES, "reply_scale": 0.5},
}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[1])
    p.add_argument("--out", type=Path, default=ROOT / "build" / "dev")
    p.add_argument("--sets", nargs="+", default=None, metavar="PATTERN")
    p.add_argument("--encounters", nargs="+", default=None, metavar="PATTERN",
                   help="only these encounters (shell patterns), e.g. a few for a quick comparison")
    p.add_argument("--schemes", nargs="+", default=["paper", "always", "pays", "pays-compressed", "lean"],
                   choices=list(GRID), help="GRID entries to run (each a CERPE run per set; cached)")
    args = p.parse_args(argv)
    entries = [s for s in dev.real_sets(ROOT / "datasets_manifest") if s.status == "ok"]
    from cerpe.synth import SUITES

    for seed in args.seeds:
        entries += [dev.synthetic_set(setting, seed, "dev", args.out, progress=False)
                    for setting in SUITES["paper-default"]]
    entries = [e for e in entries if not args.sets or any(fnmatch.fnmatchcase(e.name, q) for q in args.sets)]
    runs, errors = pareto.scheme_runs([(e.name, e.manifest, None) for e in entries], args.out / "runs",
                                      schemes={k: GRID[k] for k in args.schemes}, n_encounters=None, progress=False,
                                      only=args.encounters)
    for msg in errors:
        print(f"error: {msg}", file=sys.stderr)
    table = pareto.pareto_table(runs)
    md = "".join(f"\n### {s}\n\n{pareto.format_markdown(table, s)}" for s in table["setting"].unique())
    checks = []
    for scheme in (k for k in args.schemes if k not in ("paper", "always")):
        for s in table["setting"].unique():
            try:
                c = pareto.check(table, scheme, s)
            except pareto.ParetoError:
                continue
            checks.append(f"{scheme:12s} {s:32s} bytes/always {c['bytes_vs_always']:.3f}  image bytes/paper "
                          f"{c['image_bytes_vs_paper']:.3f}  e_rot/paper {c['e_rot_vs_paper']:.3f}  "
                          f"success/paper {c['success_vs_paper']:.3f}")
    parts = pareto.breakdown(runs)
    text = (md + "\n```\n" + "\n".join(checks) + "\n```\n\nwhere the bytes go (per robot per step) and where e_rot "
            "comes from:\n\n```\n" + parts.to_string(index=False, float_format=lambda v: f"{v:.4g}") + "\n```\n")
    print(text)
    atomic_write_text(args.out / "policy.csv", table.to_csv(index=False, float_format="%.6g"))
    atomic_write_text(args.out / "policy.md", f"# request policy on development data\n\nsets: "
                      f"{', '.join(e.name for e in entries)}\n{text}")
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
