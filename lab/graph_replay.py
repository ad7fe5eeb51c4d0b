"""Replay the pose graph (``cerpe-graph``) on recorded development runs with other settings, in seconds.

Usage::

    cerpe dev --methods cerpe cerpe-wo-em cerpe-graph      # development runs (real dev sets, seed >= 1)
    python -m lab.graph_replay [--runs build/dev/runs ...] [--set KEY=V1,V2 ...]

Every combination of the ``--set`` values (fields of the noise model
:class:`~cerpe.algorithm.graph_model.GraphModel`: the calibrated constants and the knobs of
``backend.graph`` alike; an unknown key lists the known ones) is replayed on every set's recorded
``cerpe-graph`` passes
(:func:`lab.graphdev.replay_run`: the same direct estimates, verdicts and odometry, only
the back end re-run) and judged by ``cerpe dev``'s graph checks against the set's recorded CERPE
and CERPE w/o EM runs (:func:`cerpe.pipeline.devreport.checks`): e_pos against CERPE's over all
frames and against w/o EM's over w/o EM's frames (never worse than what the graph fuses), e_rot and
success. One line
per combination: the geometric mean of the graph's e_pos over min(CERPE, w/o EM) (GT scale where a
set has no predicted scale), how many sets pass each check, and the ratio per set. Without ``--set``:
the shipped model :data:`~cerpe.algorithm.graph_model.GRAPH_MODEL`, which gives runs made with the
default tree back. Refuses paper-default runs (test data).
"""
from __future__ import annotations

import argparse
import dataclasses
import itertools
from pathlib import Path

import numpy as np

from cerpe.algorithm.graph_model import GRAPH_MODEL, GraphError, GraphModel
from cerpe.config import ConfigError, merge_conf
from cerpe.pipeline.devreport import GRAPH_CHECKS, checks, report_runs
from cerpe.pipeline.evaluate import load_run
from cerpe.pipeline.run import RunError, parse_sets

from .graphdev import GraphDevError, dev_sets, replay_run

ROOT = Path(__file__).resolve().parents[1]


def grid(pairs: list[str]) -> list[dict]:
    """``KEY=V1,V2`` strings -> every combination of the values, as GraphModel overrides."""
    keys, values = [], []
    for p in pairs:
        key, sep, vals = p.partition("=")
        if not sep or not vals:
            raise SystemExit(f"--set {p!r}: expected KEY=V1[,V2...]")
        keys.append(key.strip())
        try:  # each value as `cerpe run --set` reads one (YAML)
            values.append([parse_sets([f"{key.strip()}={v.strip()}"])[key.strip()] for v in vals.split(",")])
        except RunError as exc:
            raise SystemExit(str(exc)) from None
    return [dict(zip(keys, combo)) for combo in itertools.product(*values)]


def judge(sets: list[Path], conf: GraphModel) -> tuple[dict, list[str]]:
    """``cerpe dev``'s graph checks of the graph replayed with ``conf`` on each set: counts and per-set ratios."""
    counts, ratios, logs = {}, [], []
    for d in sets:
        runs = [(d.name, load_run(d / m)) for m in ("cerpe", "cerpe-wo-em") if (d / m / "run.json").is_file()]
        graph = load_run(d / "cerpe-graph")
        runs.append((d.name, dataclasses.replace(graph, steps=replay_run(d / "cerpe-graph", conf))))
        table, _ = report_runs(runs)
        rows = table.set_index("method")
        key = "e_pos_m" if np.isfinite(rows.loc["cerpe-graph", "e_pos_m"]) else "e_pos_gt_scale_m"
        ref = np.nanmin([rows.loc[m, key] for m in ("cerpe", "cerpe-wo-em") if m in rows.index] + [np.inf])
        r = float(rows.loc["cerpe-graph", key] / ref)
        if np.isfinite(r) and r > 0:
            ratios.append(r)
        for c in checks(table).itertuples(index=False):
            if c.check in GRAPH_CHECKS:
                counts.setdefault(c.check, [0, 0])
                counts[c.check][0] += c.result == "pass"
                counts[c.check][1] += c.result != "n/a"
        logs.append(f"{d.name.removeprefix('dev-').removeprefix('synthetic-')} {r:.3f}")
    return {"geo_ratio": float(np.exp(np.mean(np.log(ratios)))) if ratios else float("nan"), **counts}, logs


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=Path, nargs="+", default=[ROOT / "build" / "dev" / "runs"],
                   help="runs folders of `cerpe dev` outputs (default: build/dev/runs)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=V1,V2", dest="sets_config",
                   help="a GraphModel field and the values to replay it at (repeatable: every combination)")
    args = p.parse_args()
    try:
        sets = [d for runs in args.runs for d in dev_sets(runs)]
    except GraphDevError as exc:
        raise SystemExit(str(exc)) from None
    if not sets:
        raise SystemExit(f"{', '.join(map(str, args.runs))}: no cerpe-graph development runs (run `cerpe dev "
                         f"--methods cerpe cerpe-wo-em cerpe-graph` first)")
    defaults, models = dataclasses.asdict(GRAPH_MODEL), []
    for over in grid(args.sets_config) if args.sets_config else [{}]:  # every combination checked before any replay
        bad = [k for k, v in over.items()
               if k in defaults and (isinstance(v, bool) or not isinstance(v, (int, float)))]
        if bad:  # every field of the model is a number
            raise SystemExit(f"--set {bad[0]}: expected a number, got {over[bad[0]]!r}")
        try:
            models.append((over, GraphModel(**merge_conf(defaults, over, "graph model"))))
        except (ConfigError, GraphError) as exc:
            raise SystemExit(str(exc)) from None
    for over, conf in models:
        summary, per_set = judge(sets, conf)
        passed = "; ".join(f"{k.removeprefix('graph ')} {v[0]}/{v[1]}" for k, v in summary.items() if k != "geo_ratio")
        print(f"{over or 'defaults'}: graph / min(CERPE, w/o EM) geo-mean {summary['geo_ratio']:.3f}; pass: {passed}")
        print("    " + ", ".join(per_set), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
