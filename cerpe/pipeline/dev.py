"""`cerpe dev`: the development report. Tune on it, never on the paper-default suite.

Usage: ``cerpe dev [--seeds 1] [--methods ...] [--sets PATTERN ...] [--label NAME]``

Runs the methods (``cerpe``, ``cerpe-wo-em``, ``cerpe-graph``: our extension, ``sift-ransac``,
``aliked-lightglue``) over

* the real development sets: every ``datasets_manifest/dev-*.yaml`` (``enabled:
  if-present``; a set whose data is absent is skipped with a line saying so);
* synthetic development suites: both worlds rendered with development seeds
  (default 1; seed 0 is the paper-default suite, test data, and is refused), smaller
  than the paper's (``cad-intersection``: 4 encounters, one with three vehicles;
  ``indoor-team``: 2 encounters of three robots; 36 frames at 640x480, 10 Hz), with the
  paper settings' depth source and evaluation stride (``datasets_manifest/synthetic-*.yaml``);

then prints per set and method the figures of :mod:`cerpe.pipeline.devreport` (e_pos at
predicted / GT scale, e_rot mean and median, success, success after co-visibility,
placed collaborator views / image requests, anchors rejected, wrong estimates carried,
bytes per robot per step), the descriptor gate's quality per set, and the development
checks (:func:`cerpe.pipeline.devreport.checks`: a verdict per check and set).

Everything is cached and resumable under ``--out`` (default ``build/dev/``):
``synth/<sizes>/<world>-seed<N>/`` (rendered suites), ``manifests/`` (their manifests),
``runs/<set>/<method>/`` (run folders as ``cerpe run`` writes them: a run of the current
code and manifest is reused, one of older code is replaced). The report is written as
``report.{csv,md}``, ``report_gate.csv`` and ``report_checks.csv`` there; ``--label before`` also writes
``report-before.*`` so that a later session can diff before and after.
"""
from __future__ import annotations

import argparse
import fnmatch
import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from ..atomicio import atomic_write_text
from ..errors import CerpeError
from ..methods import CERPE_METHODS
from ..runfolder.current import run_is_current
from ..runfolder.provenance import code_hash, git_revision

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[2]
METHODS: tuple[str, ...] = ("cerpe", "cerpe-wo-em", "cerpe-graph", "sift-ransac",
                             "aliked-lightglue")
DEFAULT_SEEDS: tuple[int, ...] = (1,)
PAPER_SEED = 0
# Development suite sizes per paper setting (the world and the rest come from the paper-default preset):
# sized so that the whole report takes about a quarter of an hour on two cores.
SYNTH_PRESETS: dict[str, dict[str, dict]] = {
    "dev": {
        "synthetic-cad": {"n_encounters": 4, "n_three": 1, "n_frames": 36, "fps": 10.0, "size": (640, 480),
                          "n_robots": 2, "workers": 2},
        "synthetic-indoor": {"n_encounters": 2, "n_frames": 36, "fps": 10.0, "size": (640, 480), "n_robots": 3,
                             "workers": 2},
    },
    "fixture": {},  # the tiny test suite's sizes (cerpe.synth.SUITES["fixture"])
}


class DevError(CerpeError, ValueError):
    """The development report cannot run (a paper seed, an unknown method or set pattern)."""


@dataclass
class DevSet:
    """One row group of the report: a manifest to run, or why it is not run."""

    name: str
    manifest: Path | None
    status: str  # ok | skipped | error
    detail: str = ""


def real_sets(manifests_dir: Path) -> list[DevSet]:
    """The ``dev-*`` manifests of ``manifests_dir``; absent data (``if-present``) -> skipped."""
    from ..datasets import disabled_reason, find_manifests

    out = []
    for man in find_manifests(manifests_dir):
        if not man.name.startswith("dev-"):
            continue
        if man.enabled:
            out.append(DevSet(man.name, Path(man.path), "ok"))
        else:
            out.append(DevSet(man.name, Path(man.path), "skipped", disabled_reason(man)))
    return out


def synth_conf(setting: str, sizes: str, seed: int) -> tuple[str, dict]:
    """``(world, generator arguments)`` of a development suite of a paper setting."""
    from ..synth import SUITES

    world = SUITES["paper-default"][setting][0]
    base = SUITES["fixture"][setting][1] if sizes == "fixture" else SYNTH_PRESETS[sizes][setting]
    return world, {**base, "seed": int(seed)}


def _paper_manifest_fields(setting: str) -> dict:
    """The paper manifest's depth source, its options and the evaluation stride of ``setting``."""
    from ..datasets import load_manifest

    path = ROOT / "datasets_manifest" / f"{setting}.yaml"
    if not path.is_file():
        return {}
    m = load_manifest(path)
    return {"metric_depth": m.metric_depth, "metric_depth_options": dict(m.metric_depth_options),
            "evaluation": {"every": int(m.evaluation_every)}}


def synthetic_set(setting: str, seed: int, sizes: str, out: Path, progress: bool = True) -> DevSet:
    """Render (or find) one development suite and write its manifest; the set to run.

    The manifest is the generator's own (mocap layout) with the paper setting's
    ``metric_depth``, options and ``evaluation`` and the set's name; rewritten only
    when its text changes, so cached runs stay current.
    """
    import yaml

    from ..synth import generate_suite

    if int(seed) == PAPER_SEED:
        raise DevError(f"seed {PAPER_SEED} is the paper-default suite (test data): use development seeds, e.g. 1")
    world, conf = synth_conf(setting, sizes, seed)
    name = f"dev-{setting}-s{seed}" if sizes == "dev" else f"dev-{sizes}-{setting}-s{seed}"
    folder = out / "synth" / sizes / f"{world}-seed{seed}"
    generated = Path(generate_suite(world, folder, conf, force=True, progress=progress, setting=name))
    doc = yaml.safe_load(generated.read_text())
    doc.update(_paper_manifest_fields(setting))
    doc["name"] = name
    doc["data_root"] = f"../synth/{sizes}/{world}-seed{seed}"
    text = (f"# development set written by `cerpe dev`: {world} seed {seed} ({sizes} sizes); "
            f"not the paper-default suite\n" + yaml.safe_dump(doc, sort_keys=False))
    manifest = out / "manifests" / f"{name}.yaml"
    if not manifest.is_file() or manifest.read_text() != text:
        atomic_write_text(manifest, text)
    return DevSet(name, manifest, "ok")


def run_set(s: DevSet, methods: Sequence[str], runs_root: Path, preset: str = "paper",
            progress: bool = True, knob_sets: dict | None = None) -> tuple[list[tuple[str, Path]], list[str]]:
    """Run (or reuse) every method on one set; ``(finished (set, run folder) pairs, errors)``.
    ``preset``, ``knob_sets``: the cerpe methods' configuration (``cerpe dev --preset``, ``--set``);
    the stale cerpe methods run together (:func:`cerpe.pipeline.run.run_methods`: one pass per encounter)."""
    from .run import run_methods
    from .setting import load_manifest_setting

    paths = {m: runs_root / s.name / m for m in methods}
    knobs = {m: (preset, knob_sets) if m in CERPE_METHODS else ("paper", None) for m in methods}
    stale = [m for m in methods if not run_is_current(paths[m], s.manifest, m, *knobs[m])]
    ours = tuple(m for m in stale if m in CERPE_METHODS)
    groups = ([ours] if ours else []) + [(m,) for m in stale if m not in CERPE_METHODS]
    failed, errors, setting = set(), [], None
    for group in groups:
        try:
            setting = setting if setting is not None else load_manifest_setting(s.manifest)
            t0 = time.perf_counter()
            run_methods(s.manifest, {m: paths[m] for m in group}, preset=knobs[group[0]][0], sets=knobs[group[0]][1],
                        overwrite=True, progress=progress, setting=setting)
            log.info("%s/%s: %.0f s", s.name, "+".join(group), time.perf_counter() - t0)
        except CerpeError as exc:
            failed.update(group)
            errors.append(f"{s.name}/{'+'.join(group)}: {exc}")
            log.error("%s/%s: %s", s.name, "+".join(group), exc)
    return [(s.name, paths[m]) for m in methods if m not in failed], errors


def _selected(name: str, patterns: Sequence[str] | None) -> bool:
    return not patterns or any(fnmatch.fnmatchcase(name, p) for p in patterns)


def dev_report(out: Path, seeds: Sequence[int] = DEFAULT_SEEDS, methods: Sequence[str] = METHODS,
               sets: Sequence[str] | None = None, synth: str = "dev", real: bool = True,
               manifests_dir: Path | None = None, preset: str = "paper", label: str | None = None,
               progress: bool = True, echo=print, knob_sets: dict | None = None) -> dict:
    """Build (or resume) every run of the report, evaluate, print and write it (``preset``, ``knob_sets``:
    the cerpe methods' configuration, recorded in each run.json and the report; ``synth``: the
    synthetic suites' size).

    Returns ``{"table", "gate", "sets", "errors", "paths"}``; ``echo`` prints a line
    (each skipped set, the report).
    """
    from .devreport import checks, format_markdown, format_text, report

    bad = [m for m in methods if m not in METHODS]
    if bad:
        raise DevError(f"--methods {' '.join(bad)}: choose from {', '.join(METHODS)}")
    if any(int(s) == PAPER_SEED for s in seeds):
        raise DevError(f"--seeds: seed {PAPER_SEED} is the paper-default suite (test data); use development seeds")
    if any(int(s) < 0 for s in seeds):
        raise DevError(f"--seeds {' '.join(map(str, seeds))}: seeds are >= 1")
    if synth not in SYNTH_PRESETS and synth != "none":
        raise DevError(f"--synth {synth!r}: one of {', '.join([*SYNTH_PRESETS, 'none'])}")
    out = Path(out)
    t0 = time.perf_counter()
    entries: list[DevSet] = []
    if real:
        entries += real_sets(Path(manifests_dir or ROOT / "datasets_manifest"))
    real_names = {e.name for e in entries}
    if synth != "none":
        from ..synth import SUITES

        for seed in seeds:
            for setting in SUITES["paper-default"]:
                name = f"dev-{setting}-s{seed}" if synth == "dev" else f"dev-{synth}-{setting}-s{seed}"
                if _selected(name, sets):
                    entries.append(synthetic_set(setting, int(seed), synth, out, progress))
    entries = [e for e in entries if _selected(e.name, sets)]
    if sets and not entries:
        raise DevError(f"--sets {' '.join(sets)}: matches no development set")
    runs, errors = [], []
    for e in entries:
        if e.status != "ok":
            echo(f"{e.name}: skipped ({e.detail})")
            continue
        done, errs = run_set(e, methods, out / "runs", preset, progress, knob_sets)
        runs += done
        errors += errs
    table, gate = report(runs)
    check = checks(table, real=real_names)
    prov = {"git_revision": git_revision(), "code_cerpe": code_hash("cerpe"), "code_baselines": code_hash("sift-ransac"),
            "preset": preset, "sets": knob_sets or {},
            "synthetic": {"sizes": synth, "seeds": [int(s) for s in seeds]},
            "sets": {e.name: e.status + (f": {e.detail}" if e.detail else "") for e in entries},
            "methods": list(methods), "command": " ".join(sys.argv), "finished_at": time.strftime("%Y-%m-%dT%H:%M:%S")}
    text = format_text(table, gate, check)
    echo(text)
    paths = []
    for stem in ["report"] + ([f"report-{label}"] if label else []):
        for suffix, content in ((".csv", table.to_csv(index=False, float_format="%.6g")),
                                ("_gate.csv", gate.to_csv(index=False, float_format="%.6g")),
                                ("_checks.csv", check.to_csv(index=False)),
                                (".md", format_markdown(table, gate, prov, check))):
            p = out / f"{stem}{suffix}"
            atomic_write_text(p, content)
            paths.append(p)
    echo(f"written: {', '.join(str(p) for p in paths)}")
    echo(f"done in {time.perf_counter() - t0:.0f} s")
    return {"table": table, "gate": gate, "checks": check, "sets": entries, "errors": errors, "paths": paths}


# --------------------------------------------------------------------------- CLI
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=ROOT / "build" / "dev",
                   help="cache and report folder (default: build/dev in the checkout)")
    p.add_argument("--seeds", type=int, nargs="+", default=list(DEFAULT_SEEDS),
                   help="synthetic development seeds (default: %(default)s; 0, the paper-default suite, is refused)")
    p.add_argument("--methods", nargs="+", default=list(METHODS), help="methods to run (default: all five)")
    p.add_argument("--sets", nargs="+", default=None, metavar="PATTERN",
                   help="only the sets whose names match these patterns, e.g. 'dev-sun3d*' 'dev-synthetic-cad-s1'")
    p.add_argument("--synth", default="dev", choices=[*SYNTH_PRESETS, "none"],
                   help="synthetic development suite sizes: dev (default), fixture (tiny, tests), none")
    p.add_argument("--no-real", action="store_true", help="leave out the real development sets")
    p.add_argument("--manifests", type=Path, default=None,
                   help="folder of the real development manifests (default: the checkout's datasets_manifest/)")
    p.add_argument("--preset", default="paper", metavar="P",
                   help="the cerpe methods' named configuration (default: paper); `cerpe config show --presets`")
    p.add_argument("--label", default=None,
                   help="also write report-LABEL.{csv,md} (e.g. before / after) beside report.{csv,md}")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="sets_config",
                   help="a knob of the cerpe methods' configuration, as `cerpe run --set` (repeatable; "
                        "e.g. messages.share_estimates=true); use its own --out, or the runs there are replaced")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


def main(args: argparse.Namespace) -> int:
    if args.label is not None and not (args.label and all(c.isalnum() or c in "-_." for c in args.label)):
        raise DevError(f"--label {args.label!r}: letters, digits, '-', '_' and '.' only")
    from .run import parse_sets

    res = dev_report(args.out, args.seeds, args.methods, args.sets, args.synth, not args.no_real, args.manifests,
                     args.preset, args.label, progress=not args.no_progress,
                     knob_sets=parse_sets(args.sets_config) or None)
    for msg in res["errors"]:
        print(f"cerpe dev: error: {msg}", file=sys.stderr)
    return 1 if res["errors"] else 0
