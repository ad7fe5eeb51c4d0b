"""`cerpe bench`: per-step latency, peak memory and message bytes of a CERPE team.

Runs :class:`cerpe.algorithm.Team` with a backbone preset (``offline`` by
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
* accuracy figures of the same run (issue 4's checks): direct inter-robot rotation
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
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..atomicio import atomic_write_json, check_file_target
from ..errors import CerpeError
from ..geometry import e_rot, se3_inverse
from ..records import STAGES
from .evaluate import COVIS_NEGATIVE, COVIS_POSITIVE, GATE_OVERLAP, gate_quality
from .paper import PAPER_NUMBERS, ROOT

log = logging.getLogger(__name__)

# the paper's team update per robot count (never our measurement)
TARGET_MS = {2: float(PAPER_NUMBERS["ms_2"]), 3: float(PAPER_NUMBERS["ms_3"])}
DEFAULT_MANIFEST = "datasets_manifest/synthetic-indoor.yaml"


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
    parser.add_argument("--robots", type=int, nargs="+", default=[2, 3], help="team sizes to run (default: 2 3)")
    parser.add_argument("--steps", type=int, default=25, help="steps per team size (default: %(default)s)")
    parser.add_argument("--warmup", type=int, default=2, help="first steps left out of the statistics")
    parser.add_argument("--encounters", type=int, default=2, help="encounters to walk per team size")
    parser.add_argument("--all-encounters", action="store_true",
                        help="also walk every encounter of the suite, all steps, with all its robots, and print "
                             "the accuracy checks over the whole suite")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--preset", default="offline", help="backbone preset (offline | paper)")
    parser.add_argument("--depth", default=None, help="depth source (default: the manifest's metric_depth)")
    parser.add_argument("--depth-conf", default=None,
                        help='JSON options of the depth source, e.g. \'{"min_m": 0.5, "max_m": 40}\' for '
                             'an outdoor stereo sensor (default: the manifest\'s metric_depth_options; the '
                             'sensor without options sees 0.3-10 m)')
    parser.add_argument("--graph-seconds", type=float, default=60.0,
                        help="length of the encounter the graph update is timed over, at 10 Hz (default: 60)")
    parser.add_argument("--out", default=None, help="write the figures as JSON here")


def _resize(image: np.ndarray, depth: np.ndarray | None, K: Any, w: int, h: int):
    import cv2

    H, W = image.shape[:2]
    if (W, H) == (w, h):
        return image, depth, K
    img = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)
    d = None if depth is None else cv2.resize(depth, (w, h), interpolation=cv2.INTER_NEAREST)
    return img, d, K.scaled(w / W, h / H)


def _stats(x: list[float]) -> dict[str, float]:
    a = np.asarray(x, float)
    if a.size == 0:
        return {"median": float("nan"), "p90": float("nan"), "mean": float("nan"), "n": 0}
    return {"median": float(np.median(a)), "p90": float(np.percentile(a, 90)), "mean": float(a.mean()),
            "n": int(a.size)}


# a pair "overlaps" at a step when the ground-truth overlap ratio (either way) reaches the gate check's threshold
OVERLAP_MIN = GATE_OVERLAP


def _ego_steps(X: list[np.ndarray], T_world_cam: np.ndarray) -> dict[str, Any]:
    """Per-step ego-motion errors of one robot on one encounter: metric odometry ``X`` vs ground truth.

    Returns ``trans_err_m`` ``[T-1]`` (norm of the difference of the per-step relative
    translations), ``rot_err_deg`` ``[T-1]``, ``path_m`` (ground-truth path length) and
    ``end_err_m`` (position error of ``X_0^-1 X_T`` against ground truth); empty when
    ground truth is missing or the robot did not move.
    """
    T = len(X)
    gt = [np.asarray(T_world_cam[t]) for t in range(T)]
    path = sum(float(np.linalg.norm(gt[t][:3, 3] - gt[t - 1][:3, 3])) for t in range(1, T))
    if T < 2 or path <= 0 or not all(np.all(np.isfinite(g)) for g in gt):
        return {"trans_err_m": [], "rot_err_deg": [], "path_m": 0.0, "end_err_m": float("nan")}
    tr, rot = [], []
    for t in range(1, T):
        de = se3_inverse(X[t - 1]) @ X[t]
        dg = se3_inverse(gt[t - 1]) @ gt[t]
        tr.append(float(np.linalg.norm(de[:3, 3] - dg[:3, 3])))
        rot.append(float(np.degrees(e_rot(de, dg))))
    e_end = se3_inverse(X[0]) @ X[-1]
    g_end = se3_inverse(gt[0]) @ gt[-1]
    return {"trans_err_m": tr, "rot_err_deg": rot, "path_m": path,
            "end_err_m": float(np.linalg.norm(e_end[:3, 3] - g_end[:3, 3]))}


def ego_summary(runs: list[dict[str, Any]]) -> dict[str, float]:
    """Issue 4's ego-motion check over several :func:`_ego_steps` results of one robot.

    ``rpe_trans_pct``: sum of per-step translation errors / total path length (%);
    ``rpe_rot_deg_median``: median per-step rotation error (degrees);
    ``end_drift_pct``: sum of end position errors / total path length (%).
    """
    path = sum(r["path_m"] for r in runs)
    tr = [e for r in runs for e in r["trans_err_m"]]
    rot = [e for r in runs for e in r["rot_err_deg"]]
    if path <= 0 or not tr:
        return {"rpe_trans_pct": float("nan"), "rpe_rot_deg_median": float("nan"), "end_drift_pct": float("nan"),
                "path_m": float(path), "n_steps": 0}
    ends = [r["end_err_m"] for r in runs if r["path_m"] > 0]
    return {"rpe_trans_pct": 100 * float(np.sum(tr)) / path, "rpe_rot_deg_median": float(np.median(rot)),
            "end_drift_pct": 100 * float(np.nansum(ends)) / path, "path_m": float(path), "n_steps": len(tr)}


def _overlapping(enc: Any, t: int, i: int, j: int) -> bool:
    if enc.overlap is None:
        return True  # no ground truth of overlap: every direct estimate counts
    return bool(max(enc.overlap[t, i, j], enc.overlap[t, j, i]) >= OVERLAP_MIN)


def _cold_start(plugins: Any) -> None:
    """Drop the plug-ins' public caches (``clear_cache``/``clear_caches``), including the XFeat
    encoder that presets share between plug-in objects, so a run is measured from scratch."""
    seen = set()
    for obj in (plugins.descriptor, plugins.backbone, getattr(plugins.backbone, "encoder", None),
                getattr(plugins.descriptor, "encoder", None)):
        if obj is None or id(obj) in seen:
            continue
        seen.add(id(obj))
        for name in ("clear_cache", "clear_caches"):
            if callable(getattr(obj, name, None)):
                getattr(obj, name)()


def _n_encoded(plugins: Any) -> int:
    enc = getattr(plugins.backbone, "encoder", None)
    return int(getattr(enc, "n_encoded", 0))


def walk(encounters: list, n_robots: int, plugins: Any, steps: int | None, warmup: int,
         width: int, height: int) -> dict[str, Any]:
    """Walk ``encounters`` with an ``n_robots`` team (first ``steps`` steps, all when None).

    Returns latency (ms), bytes, ego-motion per robot id and direct rotation errors; the
    plug-ins' caches are cleared first, so the figures are those of a cold start.
    """
    from tqdm.auto import tqdm

    from ..algorithm import Team
    from ..protocols import FrameContext

    _cold_start(plugins)
    enc0 = _n_encoded(plugins)
    team_ms: list[float] = []
    stage_ms: dict[str, list[float]] = {s: [] for s in STAGES}
    robot_ms: list[float] = []
    bytes_kind: dict[str, list[int]] = {k: [] for k in ("descriptor", "pose", "request", "reply")}
    bytes_total: list[int] = []
    gate_open = pairs = robot_steps = all_robot_steps = gated_all = 0
    rot_direct: list[float] = []
    gate_rows: list[dict[str, Any]] = []
    ego: dict[str, list[dict[str, Any]]] = {}
    for enc in encounters:
        robots = enc.robots[:n_robots]
        ids = [r.robot_id for r in robots]
        team = Team(ids, plugins.descriptor, plugins.backbone, plugins.depth)
        T = enc.n_steps if steps is None else min(enc.n_steps, steps)
        X: dict[str, list[np.ndarray]] = {r: [] for r in ids}
        for t in tqdm(range(T), desc=f"bench {n_robots} robots {enc.name}", unit="step", leave=False):
            imgs, ctxs = [], []
            for r in robots:
                img, d, K = _resize(r.image(t), r.depth_m(t), r.intrinsics, width, height)
                imgs.append(img)
                ctxs.append(FrameContext(r.robot_id, t, K, d, 0))
            t0 = time.perf_counter()
            res = team.step(imgs, ctxs)
            dt = (time.perf_counter() - t0) * 1000
            all_robot_steps += len(res.robots)
            gated_all += sum(p.gate_open for p in res.pairs)
            for rec in res.robots:
                X[rec.robot].append(rec.T_odom_cam)
            for p in res.pairs:
                i, j = enc.robot_ids.index(p.ego), enc.robot_ids.index(p.other)
                if enc.overlap is not None:
                    gate_rows.append({"encounter": enc.name, "step": t, "ego": p.ego, "other": p.other,
                                      "gate_score": p.gate_score, "overlap_gt": float(enc.overlap[t, i, j])})
                if p.source == "direct" and p.T_cj_ci is not None:
                    gt = enc.gt_T_cj_ci(t, i, j)
                    if gt is not None and _overlapping(enc, t, i, j):
                        rot_direct.append(float(e_rot(p.T_cj_ci, gt)))
            if t < warmup:
                continue
            team_ms.append(dt)
            robot_steps += len(res.robots)
            for rec in res.robots:
                for s in STAGES:
                    stage_ms[s].append(1000 * float(rec.timings_s.get(s, 0.0)))
                robot_ms.append(1000 * float(sum(rec.timings_s.values())))
                for k in bytes_kind:
                    bytes_kind[k].append(int(rec.bytes_sent.get(k, 0)))
                bytes_total.append(rec.bytes_total)
            gate_open += sum(p.gate_open for p in res.pairs)
            pairs += len(res.pairs)
        for r in robots:
            ego.setdefault(r.robot_id, []).append(_ego_steps(X[r.robot_id], r.T_world_cam[:T]))
    return {"team_ms": team_ms, "stage_ms": stage_ms, "robot_ms": robot_ms, "bytes_kind": bytes_kind,
            "bytes_total": bytes_total, "gate_open": gate_open, "pairs": pairs, "rot_direct": rot_direct,
            "gate_rows": gate_rows,
            "ego": ego, "xfeat_passes": _n_encoded(plugins) - enc0, "robot_steps": robot_steps,
            "all_robot_steps": all_robot_steps, "cross": _cross_counts(plugins, gated_all)}


def _cross_counts(plugins: Any, gated: int) -> dict[str, int]:
    """The backbone's cross-robot registration counters over a walk (all steps; the plug-ins are
    fresh per walk) beside the gated pairs: the learned matcher should run on a part of those only."""
    counts = getattr(plugins.backbone, "counts", None) or {}
    return {"gated_pairs": int(gated), **{k: int(v) for k, v in counts.items() if k.startswith("cross-")}}


def summarise(w: dict[str, Any], n_robots: int) -> dict[str, Any]:
    """Statistics of one :func:`walk` (the figures ``format_table`` prints)."""
    rs = max(w["all_robot_steps"], 1)  # XFeat passes are counted over warm-up steps too
    return {
        "n_robots": n_robots,
        "accuracy": {
            "direct_rot_err_rad": _stats(w["rot_direct"]),
            "ego_per_robot": {r: ego_summary(v) for r, v in sorted(w["ego"].items())},
        },
        "team_step_ms": _stats(w["team_ms"]),
        "robot_step_ms": _stats(w["robot_ms"]),
        "stage_ms": {s: _stats(v) for s, v in w["stage_ms"].items()},
        "bytes_per_robot_step": {k: _stats(v) for k, v in w["bytes_kind"].items()} | {"total": _stats(w["bytes_total"])},
        "gate_open_ratio": w["gate_open"] / w["pairs"] if w["pairs"] else float("nan"),
        # XFeat network passes per robot-step (own image + received images): > 0 means the
        # encoder really ran, i.e. the run did not reuse features cached by an earlier one
        "xfeat_passes_per_robot_step": w["xfeat_passes"] / rs,
        "cross": w["cross"],
        "target_ms": TARGET_MS.get(n_robots),
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }


def bench_team(encounters: list, n_robots: int, plugins: Any, steps: int | None, warmup: int,
               width: int, height: int) -> dict[str, Any]:
    """Walk ``encounters`` cold with an ``n_robots`` team; latency/bytes/accuracy statistics."""
    return summarise(walk(encounters, n_robots, plugins, steps, warmup, width, height), n_robots)


def suite_accuracy(encounters: list, plugins: Any, width: int, height: int) -> dict[str, Any]:
    """Accuracy checks over every encounter, every step, with all of each encounter's robots.

    ``gate`` is :func:`~cerpe.pipeline.evaluate.gate_quality` of the descriptor gate over
    every ordered pair and step with ground-truth overlap, at the descriptor's ``tau``
    (None when the suite has no overlap ground truth).
    """
    import pandas as pd

    merged: dict[str, Any] = {"rot_direct": [], "ego": {}, "gate_rows": []}
    for enc in encounters:
        w = walk([enc], len(enc.robots), plugins, None, 0, width, height)
        merged["rot_direct"] += w["rot_direct"]
        merged["gate_rows"] += w["gate_rows"]
        for r, v in w["ego"].items():
            merged["ego"].setdefault(r, []).extend(v)
    tau = getattr(plugins.descriptor, "thresholds", {}).get("tau")
    gate = gate_quality(pd.DataFrame(merged["gate_rows"]), tau) if merged["gate_rows"] else None
    return {"n_encounters": len(encounters),
            "accuracy": {"direct_rot_err_rad": _stats(merged["rot_direct"]),
                         "ego_per_robot": {r: ego_summary(v) for r, v in sorted(merged["ego"].items())},
                         "gate": gate}}


def _fmt_acc(a: dict[str, Any]) -> list[str]:
    d = a["direct_rot_err_rad"]
    lines = [f"   direct relative rotation error, overlapping pairs (overlap >= {OVERLAP_MIN}): median "
             f"{d['median']:.4f} rad, p90 {d['p90']:.4f} rad, n={d['n']} (target < 0.05 rad)"]
    lines.append(f"   {'ego-motion per robot':<22}{'RPE trans %':>12}{'RPE rot deg':>12}{'end drift %':>12}"
                 f"{'path m':>9}{'steps':>7}   (targets: < 2 %, < 0.5 deg median)")
    for r, e in a["ego_per_robot"].items():
        lines.append(f"   {r:<22}{e['rpe_trans_pct']:>12.2f}{e['rpe_rot_deg_median']:>12.3f}"
                     f"{e['end_drift_pct']:>12.2f}{e['path_m']:>9.2f}{e['n_steps']:>7d}")
    g = a.get("gate")
    if g:
        lines.append(f"   descriptor gate vs GT co-visibility (unordered pairs: overlap >= {COVIS_POSITIVE} both ways "
                     f"positive, < {COVIS_NEGATIVE} both ways negative) over {g['covis_n_pairs']} pairs "
                     f"({g['covis_n_positive']} positive, {g['covis_n_left_out']} left out): ROC AUC "
                     f"{g['covis_roc_auc']:.3f} (target >= 0.90); at tau {g['tau']:.4f} precision "
                     f"{g['covis_precision']:.3f}, recall {g['covis_recall']:.3f} (targets >= 0.8)")
        lines.append(f"   old ordered label: descriptor gate vs GT overlap >= {GATE_OVERLAP} over {g['n_pairs']} ordered pairs "
                     f"({g['n_overlapping']} overlapping): ROC AUC {g['roc_auc']:.3f} (target >= 0.90); at tau "
                     f"{g['tau']:.4f} precision {g['precision']:.3f}, recall {g['recall']:.3f}, open "
                     f"{100 * g['open_rate']:.0f} %")
        lines.append(f"   the overlap ratio is directional, the cosine symmetric: {100 * g['mixed_share']:.0f} % "
                     f"of ordered pairs overlap one way only; best AUC any symmetric score can reach "
                     f"{g['roc_auc_ceiling']:.3f}; descriptor AUC on pairs whose directions agree "
                     f"{g['roc_auc_consistent']:.3f}")
    return lines


GRAPH_TARGET_MS = 10.0  # issue 20: the graph update per robot-step, median


def graph_latency(n_robots: int, seconds: float = 60.0, rate_hz: float = 10.0, direct_share: float = 0.5,
                  seed: int = 0) -> dict[str, Any]:
    """Time :meth:`~cerpe.algorithm.graph.PairGraph.step` per robot-step over a simulated encounter.

    Each robot keeps one graph per peer (``n_robots - 1``) with the default configuration;
    a robot-step's time is the sum over its graphs. Direct estimates come on a random
    ``direct_share`` of the steps with the graph's own noise levels, 5 % of them 0.5 rad wrong.
    """
    from ..algorithm import CerpeConfig
    from ..algorithm.graph import DirectEstimate, PairGraph
    from ..algorithm.graph_sim import perturb, simulate_pair

    conf = CerpeConfig().graph
    n_steps = max(int(round(seconds * rate_hz)), 2)
    rng = np.random.default_rng(seed)
    share = float(np.clip(direct_share if np.isfinite(direct_share) else 0.5, 0.02, 1.0))
    streams = []
    for k in range(n_robots * (n_robots - 1)):
        steps = [0] + [t for t in range(1, n_steps) if rng.random() < share]
        s = simulate_pair(seed + k, n_steps, speed_m=1.0 / rate_hz, odo_rot=conf.odo_rot_per_step,
                          odo_trans=conf.odo_trans_per_step, direct_steps=steps, direct_rot=conf.direct_rot_rad,
                          direct_trans=conf.direct_trans_m)
        for t in steps:
            if rng.random() < 0.05:
                s.direct[t] = perturb(rng, s.truth[t], 0.5 / np.sqrt(3), 0.5)
        streams.append((PairGraph(conf), s))
    per_robot: list[float] = []
    nodes = 0
    for t in range(n_steps):
        for r in range(n_robots):
            t0 = time.perf_counter()
            for g, s in streams[r * (n_robots - 1):(r + 1) * (n_robots - 1)]:
                d = DirectEstimate(t, s.direct[t]) if t in s.direct else None
                g.step(t, s.X_i[t], s.X_j[t], t, d)
            per_robot.append(1000 * (time.perf_counter() - t0))
    nodes = sum(g.n_nodes for g, _ in streams)
    return {"n_robots": n_robots, "seconds": float(seconds), "steps": n_steps, "direct_share": share,
            "nodes": int(nodes), "update_ms": _stats(per_robot), "target_ms": GRAPH_TARGET_MS}


def format_graph(g: dict[str, Any]) -> str:
    u = g["update_ms"]
    verdict = "met" if u["median"] < g["target_ms"] else "NOT met"
    return (f"== graph update (cerpe-graph, our extension), {g['n_robots']} robots, simulated {g['seconds']:.0f} s "
            f"encounter ({g['steps']} steps at 10 Hz, direct estimates on {100 * g['direct_share']:.0f} % of "
            f"steps, {g['nodes']} nodes in {g['n_robots'] * (g['n_robots'] - 1)} graphs): per robot-step median "
            f"{u['median']:.2f} ms, p90 {u['p90']:.2f} ms, mean {u['mean']:.2f} ms "
            f"(target < {g['target_ms']:.0f} ms median: {verdict})")


def format_table(results: list[dict[str, Any]], descriptor_info: dict[str, Any]) -> str:
    lines = []
    for r in results:
        ts = r["team_step_ms"]
        tgt = r["target_ms"]
        verdict = "" if tgt is None else (" (target %.0f ms: %s)" % (tgt, "met" if ts["median"] <= tgt else "NOT met"))
        lines.append(f"== {r['n_robots']} robots (cold start; {r['xfeat_passes_per_robot_step']:.2f} XFeat passes "
                     f"per robot-step): team step median {ts['median']:.0f} ms, p90 {ts['p90']:.0f} ms"
                     f" over {ts['n']} steps{verdict}; peak RSS {r['peak_rss_mib']:.0f} MiB;"
                     f" gate open {100 * r['gate_open_ratio']:.0f} % of pairs")
        lines.append(f"   {'stage (per robot-step)':<24}{'median ms':>10}{'p90 ms':>10}{'mean ms':>10}")
        for s, v in r["stage_ms"].items():
            lines.append(f"   {s:<24}{v['median']:>10.1f}{v['p90']:>10.1f}{v['mean']:>10.1f}")
        v = r["robot_step_ms"]
        lines.append(f"   {'all stages':<24}{v['median']:>10.1f}{v['p90']:>10.1f}{v['mean']:>10.1f}")
        lines.append(f"   {'bytes per robot-step':<24}{'median':>10}{'p90':>10}{'mean':>10}")
        for k, v in r["bytes_per_robot_step"].items():
            lines.append(f"   {k:<24}{v['median']:>10.0f}{v['p90']:>10.0f}{v['mean']:>10.0f}")
        c = r.get("cross") or {}
        if any(k != "gated_pairs" for k in c):
            lines.append(f"   cross-robot registration (all steps): {c['gated_pairs']} gated pairs, "
                         f"{c.get('cross-registered', 0)} collaborator views registered, "
                         f"{c.get('cross-none', 0)} not; learned matcher for {c.get('cross-learned', 0)} views "
                         f"({c.get('cross-learned-pairs', 0)} image pairs)")
        lines += _fmt_acc(r["accuracy"])
    lines.append(f"descriptor: {descriptor_info['dim']} values; frame bytes " +
                 ", ".join(f"{k} {v}" for k, v in descriptor_info["wire_bytes"].items()))
    return "\n".join(lines)


def _check_args(args: argparse.Namespace) -> None:
    """One clear error per impossible option (before anything is rendered or built)."""
    for flag, value, least in (("--steps", args.steps, 1), ("--warmup", args.warmup, 0),
                               ("--encounters", args.encounters, 1), ("--width", args.width, 16),
                               ("--height", args.height, 16), ("--frames", args.frames, 2),
                               ("--graph-seconds", args.graph_seconds, 1)):
        if value is not None and value < least:
            raise BenchError(f"{flag} {value}: must be >= {least}")
    bad = [n for n in args.robots if n < 2]
    if bad:
        raise BenchError(f"--robots {' '.join(map(str, args.robots))}: a team has at least 2 robots")
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
    from ..backbones.build import build_plugins
    from ..backbones.config import BackboneConfig

    _check_args(args)
    what, encounters, metric_depth, depth_options = _load_encounters(args)
    try:
        depth_conf = depth_options if args.depth_conf is None else json.loads(args.depth_conf)
    except json.JSONDecodeError as exc:
        raise BenchError(f"--depth-conf is not JSON: {exc}") from None
    if not isinstance(depth_conf, dict):
        raise BenchError(f"--depth-conf must be a JSON object, got {args.depth_conf!r}")

    def fresh() -> Any:  # new plug-in objects per run: no descriptor or match cached by an earlier run
        return build_plugins(BackboneConfig(models=args.preset), depth=args.depth or metric_depth,
                             depth_options=depth_conf)

    sizes = sorted({len(e.robots) for e in encounters})
    for n in args.robots:
        if not any(len(e.robots) >= n for e in encounters):
            raise BenchError(f"{what} has no encounter with {n} robots (encounters have {sizes} robots)")
    from ..threads import torch_threads

    print(f"bench: {what}; preset {args.preset}; {args.width}x{args.height}; torch threads {torch_threads()} "
          f"(CERPE_THREADS), OMP_NUM_THREADS="
          f"{os.environ.get('OMP_NUM_THREADS', 'unset')}, OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', 'unset')}, "
          f"{os.cpu_count()} CPUs", flush=True)
    results = []
    for n in args.robots:
        encs = [e for e in encounters if len(e.robots) >= n][: args.encounters]
        results.append(bench_team(encs, n, fresh(), args.steps, args.warmup, args.width, args.height))
    plugins = fresh()
    d = plugins.descriptor
    info = {"dim": int(d.dim), "wire_bytes": d.wire_bytes() if hasattr(d, "wire_bytes") else {}}
    report = {"manifest": what, "preset": args.preset, "width": args.width, "height": args.height,
              "torch_threads": torch_threads(), "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
              "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"), "cpu_count": os.cpu_count(),
              "descriptor": info, "results": results}
    print(format_table(results, info))
    report["graph"] = []
    for r in results:
        g = graph_latency(r["n_robots"], args.graph_seconds, direct_share=r["gate_open_ratio"])
        report["graph"].append(g)
        print(format_graph(g), flush=True)
    if args.all_encounters:
        suite = suite_accuracy(encounters, plugins, args.width, args.height)
        report["suite_accuracy"] = suite
        print(f"== accuracy over the whole suite ({suite['n_encounters']} encounters, all steps, all robots)")
        print("\n".join(_fmt_acc(suite["accuracy"])))
    if args.out:
        atomic_write_json(Path(args.out), report)
        print(f"wrote {args.out}")
    return 0
