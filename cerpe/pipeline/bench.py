"""`cerpe bench`: per-step latency, peak memory and message bytes of a CERPE team.

Runs :class:`cerpe.algorithm.Team` with a named configuration (``--preset``, ``--set``; the offline models by
default) on the encounters of a dataset manifest with 2 and 3 robots. The
default manifest is the paper's ``datasets_manifest/synthetic-indoor.yaml``
(three robots in every encounter): its suite is rendered on first use into the
same cache ``make paper`` uses (``build/synth/paper-default/``), so a fresh clone
renders it once and a clone after ``make paper`` renders nothing. It reports:

* team step latency (all robots of one synchronous round, sequentially in this
  process): median and p90 in ms, first ``--warmup`` steps excluded;
* per robot and step, by stage (``encode``, ``descriptor``, ``gate``,
  ``backbone``, ``scale``, ``propagation``: ``RobotRecord.timings_s``);
* message bytes per robot per step by kind (``RobotRecord.bytes_sent``) and the
  descriptor frame size in fp32/fp16/int8;
* peak resident memory of the process (``ru_maxrss``);
* the backbone's cross-robot registration counters (offline backbone): gated pairs,
  collaborator views registered, views and image pairs the learned matcher ran on;
* the pose-graph back end of ``cerpe-graph`` (our extension): its update per robot-step
  (median, p90) over a ``--graph-seconds`` (60 s) encounter at 10 Hz per team size, each
  robot updating one graph per peer; fed a simulated stream (odometry and direct
  estimates with the graph's own noise levels, 5 % of them 0.5 rad wrong) with direct
  estimates on the share of steps the gate opened in the walk above, since walking the
  backbone for 600 steps per robot would take far longer than the graph itself;
* accuracy figures of the same run: direct inter-robot rotation
  error (rad) on overlapping pairs, and per robot the per-step relative pose error
  (sum of per-step translation errors / path length, median per-step rotation
  error) and the end drift; ``--all-encounters`` adds them over the whole suite,
  with the descriptor gate's ROC AUC, precision and recall at ``tau`` against the
  co-visibility label (unordered pairs: overlap >= 0.2 both ways positive, < 0.05 both
  ways negative, the rest left out) and, beside it, against the old ordered label (with
  the best AUC any symmetric score could reach on the same pairs).

Every team size starts cold: the plug-ins' caches (XFeat features, matches) are
cleared first, and the table prints how many XFeat passes ran per robot-step.

A 2-robot run uses the first two robots of an encounter, a 3-robot run needs an
encounter with at least three. Images are resized to ``--width x --height``
(intrinsics and depth alike) when they differ. The paper's figures (RTX 4080
laptop, VGGT) are 438 ms per update for two robots and 780 ms for three; the
benchmark prints the comparison but never fails on it.

This module is the command (options, encounters, the run); the walk and its figures are in
:mod:`cerpe.pipeline.bench_walk`, the graph timing in :mod:`cerpe.pipeline.bench_graph`, the
printed table in :mod:`cerpe.pipeline.bench_report`.
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Any

from ..atomicio import atomic_write_json, check_file_target
from ..errors import CerpeError
from .bench_graph import graph_latency
from .bench_report import format_accuracy, format_graph, format_sweep, format_table
from .bench_walk import bench_team, suite_accuracy
from .paper import ROOT

DEFAULT_MANIFEST = "datasets_manifest/synthetic-indoor.yaml"
MAX_TEAM = 8  # the largest team the bench renders an encounter for
TEAM_SEED = 7  # seed of that indoor-team encounter (not the paper-default suite's)


class BenchError(CerpeError, ValueError):
    """The benchmark cannot run (no manifest, no encounter with enough robots)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--manifest", default=None,
                        help=f"dataset manifest (default: the checkout's {DEFAULT_MANIFEST}, rendered on first use "
                             f"into the cache `make paper` uses), or one written by `cerpe synth`")
    parser.add_argument("--synth", nargs="+", metavar="SETTING:INDEX", default=None,
                        help="render these encounters of the paper-default suite in memory instead of "
                             "reading --manifest (e.g. synthetic-indoor:0 synthetic-cad:6)")
    parser.add_argument("--frames", type=int, default=None, help="frames per rendered encounter (--synth)")
    parser.add_argument("--robots", type=int, nargs="+", default=[2, 3],
                        help="team sizes to run (default: 2 3); a size beyond the manifest's encounters (up to "
                             f"{MAX_TEAM}) runs every size on one rendered indoor-team encounter of that many robots")
    parser.add_argument("--steps", type=int, default=25, help="steps per team size (default: %(default)s)")
    parser.add_argument("--warmup", type=int, default=2, help="first steps left out of the statistics")
    parser.add_argument("--encounters", type=int, default=2, help="encounters to walk per team size")
    parser.add_argument("--all-encounters", action="store_true",
                        help="also walk every encounter of the suite, all steps, with all its robots, and print "
                             "the accuracy checks over the whole suite")
    parser.add_argument("--registration", choices=("worker", "inline"), default="worker",
                        help="worker (default): a received image is registered by a worker thread and its "
                             "estimate lands when ready, as a robot online; inline: in the step's joint pass, "
                             "as `cerpe run` (every estimate at its step)")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--preset", default="paper", metavar="P",
                        help="a named configuration (default: paper, the paper's protocol); `cerpe config show "
                             "--presets` lists them")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="sets",
                        help="a knob of the configuration tree, as `cerpe run --set`, e.g. backbone.models=paper")
    parser.add_argument("--depth", default=None, help="depth source (default: the manifest's metric_depth)")
    parser.add_argument("--depth-conf", default=None,
                        help='JSON options of the depth source, e.g. \'{"min_m": 0.5, "max_m": 40}\' for '
                             'an outdoor stereo sensor (default: the manifest\'s metric_depth_options; the '
                             'sensor without options sees 0.3-10 m)')
    parser.add_argument("--graph-seconds", type=float, default=60.0,
                        help="length of the encounter the graph update is timed over, at 10 Hz (default: 60)")
    parser.add_argument("--out", default=None, help="write the figures as JSON here")


def _check_args(args: argparse.Namespace) -> None:
    """One clear error per impossible option (before anything is rendered or built)."""
    for flag, value, least in (("--steps", args.steps, 1), ("--warmup", args.warmup, 0),
                               ("--encounters", args.encounters, 1), ("--width", args.width, 16),
                               ("--height", args.height, 16), ("--frames", args.frames, 2),
                               ("--graph-seconds", args.graph_seconds, 1)):
        if value is not None and value < least:
            raise BenchError(f"{flag} {value}: must be >= {least}")
    bad = [n for n in args.robots if not 2 <= n <= MAX_TEAM]
    if bad:
        raise BenchError(f"--robots {' '.join(map(str, args.robots))}: a team has 2 to {MAX_TEAM} robots")
    if args.warmup >= args.steps:
        raise BenchError(f"--warmup {args.warmup} leaves none of --steps {args.steps} to measure; "
                         f"use fewer warm-up steps or more steps")
    if args.out:
        out = Path(args.out)
        if out.is_dir():
            raise BenchError(f"--out {out}: is a folder; give a file name (e.g. {out / 'bench.json'})")
        check_file_target(out, "--out")


def _synth_specs(specs: list[str], suites: dict) -> list[tuple[str, int]]:
    """``SETTING:INDEX`` strings -> ``(setting, index)`` of the paper-default suite, checked."""
    known = suites["paper-default"]
    out = []
    for spec in specs:
        name, _, index = spec.partition(":")
        if name not in known or not index.isdigit():
            raise BenchError(f"--synth {spec!r}: expected SETTING:INDEX with SETTING one of {sorted(known)} "
                             f"and INDEX an encounter number, e.g. synthetic-indoor:0")
        n = known[name][1]["n_encounters"]
        if int(index) >= n:
            raise BenchError(f"--synth {spec!r}: the paper-default suite has encounters 0..{n - 1} of {name}")
        out.append((name, int(index)))
    return out


def _team_encounter(n: int, steps: int, width: int, height: int) -> Any:
    """One indoor-team encounter of ``n`` robots, ``steps`` frames at 10 Hz, rendered in memory
    (seed :data:`TEAM_SEED`)."""
    from ..synth import render_encounter

    print(f"bench: rendering an indoor-team encounter of {n} robots, {steps} frames at {width}x{height}", flush=True)
    conf = {"n_robots": int(n), "n_frames": max(int(steps), 2), "fps": 10.0, "size": (int(width), int(height))}
    return render_encounter("indoor-team", seed=TEAM_SEED, index=0, conf=conf, progress=True)


def _load_encounters(args: argparse.Namespace) -> tuple[str, list, str | None, dict]:
    """``(what, encounters, metric_depth, depth_options)`` of the manifest or the ``--synth`` specs."""
    from ..datasets import load_setting

    if args.synth:
        from ..synth import SUITES, render_encounter, sensor_options

        encounters = []
        for name, index in _synth_specs(args.synth, SUITES):
            world, conf = SUITES["paper-default"][name]
            conf = {k: v for k, v in conf.items() if k != "workers"}
            if args.frames:
                conf["n_frames"] = args.frames
            encounters.append(render_encounter(world, seed=conf.get("seed", 0), index=index, conf=conf,
                                               progress=True))
        depth_options = sensor_options(encounters[0].meta.get("world", "")) if encounters else {}
        return "<in-memory: " + " ".join(args.synth) + ">", encounters, "sensor", depth_options
    path = Path(args.manifest) if args.manifest else ROOT / DEFAULT_MANIFEST
    if not path.is_file():
        hint = ("" if args.manifest else
                " (the default needs a source checkout; pass --manifest, e.g. one written by `cerpe synth`)")
        raise BenchError(f"--manifest {path}: {'not a file' if path.exists() else 'not found'}{hint}")
    setting = load_setting(path)
    return str(path), setting.encounters, setting.metric_depth, setting.metric_depth_options


def main(args: argparse.Namespace) -> int:
    from .. import method_config
    from ..backbones.build import build_plugins
    from .run import parse_sets

    _check_args(args)
    try:
        tree = method_config.build(args.preset, "cerpe", parse_sets(args.sets))
    except method_config.ConfigError as exc:
        raise BenchError(str(exc)) from None
    what, encounters, metric_depth, depth_options = _load_encounters(args)
    try:
        depth_conf = depth_options if args.depth_conf is None else json.loads(args.depth_conf)
    except json.JSONDecodeError as exc:
        raise BenchError(f"--depth-conf is not JSON: {exc}") from None
    if not isinstance(depth_conf, dict):
        raise BenchError(f"--depth-conf must be a JSON object, got {args.depth_conf!r}")

    def fresh() -> Any:  # new plug-in objects per run: no descriptor or match cached by an earlier run
        return build_plugins(tree.backbone, depth=args.depth or metric_depth, depth_options=depth_conf)

    sizes = sorted({len(e.robots) for e in encounters})
    if max(args.robots) > max(sizes):  # a team sweep: every size on one encounter of the largest team
        team = _team_encounter(max(args.robots), args.steps, args.width, args.height)
        what = f"<in-memory: indoor-team seed {TEAM_SEED}, {len(team.robots)} robots, {team.n_steps} steps>"
        encounters, metric_depth = [team], "sensor"
        from ..synth import sensor_options

        depth_conf = sensor_options("indoor-team") if args.depth_conf is None else depth_conf
    from ..threads import apply_threads, blas_threads, torch_threads

    apply_threads()  # as the encoder does on its first use: the header says what the run had
    from ..algorithm import WorkerRegistrar

    registrar = WorkerRegistrar if args.registration == "worker" else None

    precision = None  # the XFeat precision that runs (offline models)
    if tree.backbone.models == "offline":
        from ..backbones.xfeat_net import resolve_precision

        precision = resolve_precision(tree.backbone.offline.precision)
    models = tree.backbone.models + (f", XFeat {precision}" if precision else "")
    print(f"bench: {what}; preset {args.preset}, models {models}; {args.width}x{args.height}; "
          f"registration {args.registration}; load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}; "
          f"torch and BLAS threads {torch_threads()} / {blas_threads()} "
          f"(CERPE_THREADS), OMP_NUM_THREADS="
          f"{os.environ.get('OMP_NUM_THREADS', 'unset')}, OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', 'unset')}, "
          f"{os.cpu_count()} CPUs", flush=True)
    results = []
    for n in args.robots:
        encs = [e for e in encounters if len(e.robots) >= n][: args.encounters]
        results.append(bench_team(encs, n, fresh(), args.steps, args.warmup, args.width, args.height, tree,
                                  registrar))
    plugins = fresh()
    d = plugins.descriptor
    info = {"dim": int(d.dim), "wire_bytes": d.wire_bytes() if hasattr(d, "wire_bytes") else {}}
    report = {"manifest": what, "preset": args.preset, "sets": parse_sets(args.sets), "xfeat_precision": precision,
              "width": args.width, "height": args.height, "registration": args.registration,
              "load_average": list(os.getloadavg()),
              "torch_threads": torch_threads(), "blas_threads": blas_threads(), "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
              "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"), "cpu_count": os.cpu_count(),
              "descriptor": info, "results": results}
    print(format_table(results, info))
    if len(results) > 1:
        print(format_sweep(results))
    report["graph"] = []
    for r in results:
        g = graph_latency(r["n_robots"], args.graph_seconds, direct_share=r["gate_open_ratio"])
        report["graph"].append(g)
        print(format_graph(g), flush=True)
    if args.all_encounters:
        suite = suite_accuracy(encounters, plugins, args.width, args.height, tree)
        report["suite_accuracy"] = suite
        print(f"== accuracy over the whole suite ({suite['n_encounters']} encounters, all steps, all robots)")
        print("\n".join(format_accuracy(suite["accuracy"])))
    if args.out:
        atomic_write_json(Path(args.out), report)
        print(f"wrote {args.out}")
    return 0
