"""`cerpe bench`'s measurement: a CERPE team walked cold over encounters, timed per step and stage,
its message bytes counted, and the accuracy figures of the same run (direct inter-robot rotation
error on overlapping pairs, per-robot ego-motion error, the descriptor gate against ground-truth
co-visibility). What the figures mean: :mod:`cerpe.pipeline.bench`.
"""
from __future__ import annotations

import resource
import time
from typing import Any, Callable

import numpy as np

from ..geometry import e_rot, se3_inverse
from ..records import STAGES
from .evaluate import GATE_OVERLAP, gate_quality
from .paper import PAPER_NUMBERS

# the paper's team update per robot count (never our measurement)
TARGET_MS = {2: float(PAPER_NUMBERS["ms_2"]), 3: float(PAPER_NUMBERS["ms_3"])}
# what a controller at 10 Hz asks of one robot's step at 640x480 (median, ms; the p90 asked: ROBOT_TARGET_P90_MS)
ROBOT_TARGET_MS = {2: 100.0, 3: 120.0}
ROBOT_TARGET_P90_MS = 150.0
TEAM_GROWTH_MAX = 1.5  # a robot's step in the largest team at most this times its step in a team of two


def _resize(image: np.ndarray, depth: np.ndarray | None, K: Any, w: int, h: int):
    import cv2

    H, W = image.shape[:2]
    if (W, H) == (w, h):
        return image, depth, K
    img = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)
    d = None if depth is None else cv2.resize(depth, (w, h), interpolation=cv2.INTER_NEAREST)
    return img, d, K.scaled(w / W, h / H)


def median_p90(x: list[float]) -> dict[str, float]:
    """Median, p90, mean and count of ``x`` (NaN and 0 when empty)."""
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
    """The ego-motion check over several :func:`_ego_steps` results of one robot.

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
         width: int, height: int, config: Any = None, registrar: Callable | None = None) -> dict[str, Any]:
    """Walk ``encounters`` with an ``n_robots`` team (first ``steps`` steps, all when None) of
    configuration ``config`` (None: the paper's protocol, :class:`~cerpe.algorithm.AlgorithmConfig`).
    ``registrar``: each robot's registrar from the backbone (received images registered apart from the
    step, :class:`~cerpe.algorithm.WorkerRegistrar`); None: in the step's joint pass.

    Returns latency (ms: wall, and CPU of the thread that ran each stage), bytes, ego-motion per robot
    id, direct rotation errors and the registrations' lateness; the plug-ins' caches are cleared first,
    so the figures are those of a cold start.
    """
    from tqdm.auto import tqdm

    from ..algorithm import Team
    from ..algorithm.registrar import merge_stats
    from ..protocols import FrameContext

    _cold_start(plugins)
    enc0 = _n_encoded(plugins)
    team_ms: list[float] = []
    team_cpu_ms: list[float] = []  # the whole process: every thread, workers' included
    stage_ms: dict[str, list[float]] = {s: [] for s in STAGES}
    stage_cpu_ms: dict[str, list[float]] = {s: [] for s in STAGES}
    robot_ms: list[float] = []  # the robot's own work: all stages less a depth sensor's part (MetricDepthSource)
    robot_cpu_ms: list[float] = []
    sensor_ms: list[float] = []  # reading or simulating a sensor's depth (in "scale")
    score_ms: list[float] = []
    score_cpu_ms: list[float] = []
    pass_ms: dict[str, list[float]] = {}  # the backbone's own profile of its pass, by part (robot-steps with a pass)
    bytes_kind: dict[str, list[int]] = {k: [] for k in ("descriptor", "pose", "request", "reply")}
    bytes_total: list[int] = []
    gate_open = pairs = robot_steps = all_robot_steps = gated_all = 0
    rot_direct: list[float] = []
    gate_rows: list[dict[str, Any]] = []
    ego: dict[str, list[dict[str, Any]]] = {}
    lateness: list[tuple[int, float]] = []
    reg_stats: list[dict[str, float]] = []
    for enc in encounters:
        robots = enc.robots[:n_robots]
        ids = [r.robot_id for r in robots]
        team = Team(ids, plugins.descriptor, plugins.backbone, plugins.depth, config, registrar=registrar)
        T = enc.n_steps if steps is None else min(enc.n_steps, steps)
        X: dict[str, list[np.ndarray]] = {r: [] for r in ids}
        for t in tqdm(range(T), desc=f"bench {n_robots} robots {enc.name}", unit="step", leave=False):
            imgs, ctxs = [], []
            for r in robots:
                img, d, K = _resize(r.image(t), r.depth_m(t), r.intrinsics, width, height)
                imgs.append(img)
                ctxs.append(FrameContext(r.robot_id, t, K, d, 0))
            t0, c0 = time.perf_counter(), time.process_time()
            res = team.step(imgs, ctxs)
            dt, dc = (time.perf_counter() - t0) * 1000, (time.process_time() - c0) * 1000
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
            team_cpu_ms.append(dc)
            robot_steps += len(res.robots)
            for rec in res.robots:
                for s in STAGES:
                    stage_ms[s].append(1000 * float(rec.timings_s.get(s, 0.0)))
                    stage_cpu_ms[s].append(1000 * float(rec.cpu_s.get(s, 0.0)))
                sensor = float(rec.parts_s.get("sensor", 0.0))
                sensor_ms.append(1000 * sensor)
                robot_ms.append(1000 * (float(sum(rec.timings_s.get(s, 0.0) for s in STAGES)) - sensor))
                robot_cpu_ms.append(1000 * (float(sum(rec.cpu_s.get(s, 0.0) for s in STAGES))
                                            - float(rec.cpu_s.get("sensor", 0.0))))
                score_ms.append(1000 * float(rec.parts_s.get("gate_score", 0.0)))
                score_cpu_ms.append(1000 * float(rec.cpu_s.get("gate_score", 0.0)))
                for k, v in rec.parts_s.items():
                    if k.startswith("backbone:"):
                        pass_ms.setdefault(k.split(":", 1)[1], []).append(1000 * float(v))
                for k in bytes_kind:
                    bytes_kind[k].append(int(rec.bytes_sent.get(k, 0)))
                bytes_total.append(rec.bytes_total)
            gate_open += sum(p.gate_open for p in res.pairs)
            pairs += len(res.pairs)
        for r in robots:
            ego.setdefault(r.robot_id, []).append(_ego_steps(X[r.robot_id], r.T_world_cam[:T]))
        lateness += [x for a in team.agents for x in a.s.registration_lateness]
        unlanded = sum(len(a.s.pending) for a in team.agents)
        reg_stats.append({**merge_stats([r.stats() for r in team.registrars]), "unlanded_at_end": unlanded})
        team.close()
    return {"team_ms": team_ms, "team_cpu_ms": team_cpu_ms, "stage_ms": stage_ms, "stage_cpu_ms": stage_cpu_ms,
            "robot_ms": robot_ms, "robot_cpu_ms": robot_cpu_ms, "sensor_ms": sensor_ms, "score_ms": score_ms, "score_cpu_ms": score_cpu_ms,
            "pass_ms": pass_ms,
            "bytes_kind": bytes_kind, "bytes_total": bytes_total, "gate_open": gate_open, "pairs": pairs,
            "rot_direct": rot_direct, "gate_rows": gate_rows, "lateness": lateness,
            "registration": merge_stats(reg_stats) if registrar is not None else None,
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
    n = max(w["robot_steps"], 1)
    reg = w.get("registration")
    late = w.get("lateness") or []
    return {
        "n_robots": n_robots,
        "accuracy": {
            "direct_rot_err_rad": median_p90(w["rot_direct"]),
            "ego_per_robot": {r: ego_summary(v) for r, v in sorted(w["ego"].items())},
        },
        "team_step_ms": median_p90(w["team_ms"]),
        "robot_step_ms": median_p90(w["robot_ms"]),
        "robot_step_cpu_ms": median_p90(w["robot_cpu_ms"]),
        # the depth sensor's part of "scale" (0 for a depth network): left out of robot_step_ms
        "sensor_ms": median_p90(w["sensor_ms"]),
        "robot_step_with_sensor_ms": median_p90([a + b for a, b in zip(w["robot_ms"], w["sensor_ms"])]),
        # the process's CPU per robot-step: every thread (registration workers, OpenCV's) included
        "process_cpu_ms_per_robot_step": float(np.sum(w["team_cpu_ms"])) / n,
        "stage_ms": {s: median_p90(v) for s, v in w["stage_ms"].items()},
        "stage_cpu_ms": {s: median_p90(v) for s, v in w["stage_cpu_ms"].items()},
        "gate_score_ms": median_p90(w["score_ms"]),
        "gate_score_cpu_ms": median_p90(w["score_cpu_ms"]),
        "backbone_pass_ms": {k: median_p90(v) for k, v in w.get("pass_ms", {}).items()},
        "bytes_per_robot_step": {k: median_p90(v) for k, v in w["bytes_kind"].items()} | {"total": median_p90(w["bytes_total"])},
        "gate_open_ratio": w["gate_open"] / w["pairs"] if w["pairs"] else float("nan"),
        # XFeat network passes per robot-step (own image + received images): > 0 means the
        # encoder really ran, i.e. the run did not reuse features cached by an earlier one
        "xfeat_passes_per_robot_step": w["xfeat_passes"] / rs,
        "cross": w["cross"],
        "registration": None if reg is None else {
            **reg, "worker_cpu_ms_per_robot_step": 1000 * reg.get("worker_cpu_s", 0.0) / rs,
            "late_steps": median_p90([s for s, _ in late]), "late_ms": median_p90([1000 * x for _, x in late]),
            "landed_late": int(sum(s > 0 for s, _ in late)), "landed": len(late)},
        "target_ms": TARGET_MS.get(n_robots),
        "robot_target_ms": ROBOT_TARGET_MS.get(n_robots),
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }


def bench_team(encounters: list, n_robots: int, plugins: Any, steps: int | None, warmup: int,
               width: int, height: int, config: Any = None, registrar: Callable | None = None) -> dict[str, Any]:
    """Walk ``encounters`` cold with an ``n_robots`` team; latency/bytes/accuracy statistics."""
    return summarise(walk(encounters, n_robots, plugins, steps, warmup, width, height, config, registrar), n_robots)


def suite_accuracy(encounters: list, plugins: Any, width: int, height: int, config: Any = None) -> dict[str, Any]:
    """Accuracy checks over every encounter, every step, with all of each encounter's robots.

    ``gate`` is :func:`~cerpe.pipeline.evaluate.gate_quality` of the descriptor gate over
    every ordered pair and step with ground-truth overlap, at the descriptor's ``tau``
    (None when the suite has no overlap ground truth).
    """
    import pandas as pd

    merged: dict[str, Any] = {"rot_direct": [], "ego": {}, "gate_rows": []}
    for enc in encounters:
        w = walk([enc], len(enc.robots), plugins, None, 0, width, height, config)
        merged["rot_direct"] += w["rot_direct"]
        merged["gate_rows"] += w["gate_rows"]
        for r, v in w["ego"].items():
            merged["ego"].setdefault(r, []).extend(v)
    tau = getattr(plugins.descriptor, "thresholds", {}).get("tau")
    gate = gate_quality(pd.DataFrame(merged["gate_rows"]), tau) if merged["gate_rows"] else None
    return {"n_encounters": len(encounters),
            "accuracy": {"direct_rot_err_rad": median_p90(merged["rot_direct"]),
                         "ego_per_robot": {r: ego_summary(v) for r, v in sorted(merged["ego"].items())},
                         "gate": gate}}
