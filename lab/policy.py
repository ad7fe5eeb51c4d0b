"""Tune the image-request policy on development data (never on the paper-default suite).

Runs CERPE with the paper's protocol, always-send and the request policy at a few
settings (``GRID``: a named preset of :mod:`cerpe.method_config` and dotted overrides) on the
development sets of ``cerpe dev`` (synthetic suites of seed >= 1 and the real
``datasets_manifest/dev-*.yaml`` sets whose data is present), every encounter, and prints the
Pareto table (``cerpe.pipeline.pareto``) per set and over all, with each policy setting's bytes,
e_rot and success against the paper's protocol and always-send (:func:`cerpe.pipeline.pareto.check`).

    python -m lab.policy [--seeds 1] [--out build/dev] [--sets PATTERN ...] [--encounters PATTERN ...]

Runs are cached in ``<out>/runs/<set>/pareto-<name>/`` (resumed; a changed setting
is a new run); the table goes to ``<out>/policy.{csv,md}``.
"""
from __future__ import annotations

import argparse
import dataclasses
import fnmatch
import sys
from pathlib import Path

from cerpe.method_config import PRESETS

from cerpe.atomicio import atomic_write_text
from cerpe.errors import CerpeError
from cerpe.pipeline import dev, pareto
from cerpe.runfolder.current import run_is_current

ROOT = Path(__file__).resolve().parents[1]

# Dotted overrides shared by several entries of the grid. On preset "pays-compressed": grey replies and the
# back-off from gates whose images place nothing, without the "lean" preset's later rules (LEAN before them).
LEAN_V1 = {"policy.miss_limit": 3, "policy.miss_backoff_steps": 3, "messages.reply_codec": "webp-grey"}
TIGHT = {"policy.max_sigma_rot_rad": 0.03, "policy.max_sigma_pos_m": 0.15, "policy.max_steps": 15}
COMPRESSED = {k: v for k, v in PRESETS["pays-compressed"].items() if k.startswith("messages.")}
PE_U2 = {"policy.backoff_pending_exempt": True, "policy.unanchored_backoff_steps": 2}
RC2 = {"policy.recheck_rot_rad": 0.03, "policy.recheck_limit": 2}
# name -> (preset of cerpe.method_config.PRESETS, dotted overrides on top); "paper" and "always" are the
# references of the check
GRID: dict[str, tuple[str, dict]] = {
    "paper": ("paper", {}),
    "always": ("always", {}),
    "pays": ("pays", {}),  # PolicyConfig's defaults
    "pays-tight": ("pays", TIGHT),
    "pays-loose": ("pays", {"policy.max_sigma_rot_rad": 0.1, "policy.max_sigma_pos_m": 0.6, "policy.max_steps": 60}),
    "pays-compressed": ("pays-compressed", {}),
    "pc-s75": ("pays-compressed", {"messages.reply_scale": 0.75}),
    "pc-s50": ("pays-compressed", {"messages.reply_scale": 0.5}),
    "pc-q50": ("pays-compressed", {"messages.reply_quality": 50}),
    "gate-compressed": ("paper", COMPRESSED),
    "pays-int8": ("pays", {"messages.descriptor_codec": "pca-int8"}),
    "pays-webp": ("pays", {"messages.reply_codec": "webp", "messages.reply_quality": 75}),
    "pi-j75": ("pays", {"messages.descriptor_codec": "pca-int8", "messages.reply_quality": 75}),
    "pi-j50": ("pays", {"messages.descriptor_codec": "pca-int8", "messages.reply_quality": 50}),
    "lean": ("lean", {}),  # = "lean-pe-u2-rc-l1" below; the entries below start from LEAN_V1
    "lean-v1": ("pays-compressed", LEAN_V1),  # back-off every 3 steps after 3 misses, nothing else
    "lean-colour": ("pays-compressed", {**LEAN_V1, "messages.reply_codec": "webp"}),  # before the grey replies
    "lean-g60": ("pays-compressed", {**LEAN_V1, "messages.reply_quality": 60}),
    "lean-g90": ("pays-compressed", {**LEAN_V1, "messages.reply_quality": 90}),  # the grey codec's quality?
    "lean-tight": ("pays-compressed", {**LEAN_V1, **TIGHT}),  # spends the grey replies' bytes on fresher anchors
    "pi-backoff": ("pays", {"policy.miss_limit": 3, "policy.miss_backoff_steps": 3,
                            "messages.descriptor_codec": "pca-int8"}),
    # replace a doubtful anchor sooner instead of asking more often (pe: a pair whose candidates wait to verify does
    # not back off; u2: a pair without an anchor waits 2 steps, not 3; rc: ask again while the estimate that set the
    # anchor disagreed by > 0.03 rad with what verified it, up to 2 in a row; b2: back off after 2 misses)
    "lean-pe": ("pays-compressed", {**LEAN_V1, "policy.backoff_pending_exempt": True}),
    "lean-pe-u2": ("pays-compressed", {**LEAN_V1, **PE_U2}),
    "lean-pe-rc": ("pays-compressed", {**LEAN_V1, "policy.backoff_pending_exempt": True, **RC2}),
    "lean-pe-u2-rc": ("pays-compressed", {**LEAN_V1, **PE_U2, **RC2}),
    "lean-pe-u2-rc-b2": ("pays-compressed", {**LEAN_V1, **PE_U2, **RC2, "policy.miss_limit": 2}),
    # fewer rechecks for margin on bytes: a looser threshold (rc04: 0.04 rad) or one recheck at most (l1)
    "lean-pe-u2-rc04": ("pays-compressed", {**LEAN_V1, **PE_U2, **RC2, "policy.recheck_rot_rad": 0.04}),
    "lean-pe-u2-rc-l1": ("pays-compressed", {**LEAN_V1, **PE_U2, **RC2, "policy.recheck_limit": 1}),
    "lean-pe-u2-rc-l1-b2": ("pays-compressed", {**LEAN_V1, **PE_U2, **RC2, "policy.recheck_limit": 1,
                                                "policy.miss_limit": 2}),
    "gate-s50": ("paper", {**COMPRESSED, "messages.reply_scale": 0.5}),
    "pc-s50-tight": ("pays-compressed", {"policy.max_sigma_rot_rad": 0.025, "policy.max_sigma_pos_m": 0.15,
                                         "policy.max_steps": 10, "messages.reply_scale": 0.5}),
}


def grid_runs(entries, runs_root: Path, names: list[str], only: list[str] | None) -> tuple[list, list[str]]:
    """Run (or find) each GRID entry of ``names`` on every encounter of each set (``only``: those matching one
    of these shell patterns) into ``<runs_root>/<set>/pareto-<name>/``: :func:`cerpe.pipeline.pareto.scheme_runs`
    for settings that are a preset and dotted overrides. Returns ``(runs, error lines)``."""
    from cerpe.pipeline.run import run_method
    from cerpe.pipeline.setting import load_manifest_setting

    out, errors = [], []
    for e in entries:
        setting = None
        for name in names:
            preset, sets = GRID[name]
            path = pareto.run_dir(runs_root, e.name, name)
            try:
                if setting is None:
                    setting = load_manifest_setting(e.manifest)
                encs = [x for x in setting.encounters if not only or any(fnmatch.fnmatchcase(x.name, q) for q in only)]
                if not encs:
                    continue
                if not run_is_current(path, e.manifest, "cerpe", preset, sets, [x.name for x in encs]):
                    run_method(e.manifest, "cerpe", path, preset=preset, sets=sets, overwrite=True, progress=False,
                               setting=dataclasses.replace(setting, encounters=encs))
                out.append(pareto.SchemeRun(e.name, name, path))
            except CerpeError as exc:
                errors.append(f"{e.name}/pareto-{name}: {exc}")
    return out, errors


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
    runs, errors = grid_runs(entries, args.out / "runs", args.schemes, args.encounters)
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
