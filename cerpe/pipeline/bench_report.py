"""`cerpe bench`'s report: the printed latency, bytes and accuracy table of each team size, the graph
update's line, and the report's latencies as rows for the paper's communication figure.
"""
from __future__ import annotations

import math
from typing import Any

from .bench_walk import OVERLAP_MIN, ROBOT_TARGET_P90_MS, TEAM_GROWTH_MAX
from .evaluate import COVIS_NEGATIVE, COVIS_POSITIVE, GATE_OVERLAP

# the ego-motion check's targets: per-step translation error summed over the path, median per-step rotation error
EGO_RPE_TRANS_MAX_PCT = 2.0
EGO_RPE_ROT_MAX_DEG = 0.5

def _ego_verdict(e: dict[str, Any]) -> str:
    """``met``, ``NOT met`` (naming the figure over its target) or ``n/a`` (no path, no steps)."""
    trans, rot = e["rpe_trans_pct"], e["rpe_rot_deg_median"]
    if math.isnan(trans) or math.isnan(rot):  # the robot did not move, or no ground truth
        return "n/a"
    over = [name for name, v, bound in (("trans", trans, EGO_RPE_TRANS_MAX_PCT), ("rot", rot, EGO_RPE_ROT_MAX_DEG))
            if not v < bound]
    return "met" if not over else f"NOT met ({', '.join(over)})"


def format_accuracy(a: dict[str, Any]) -> list[str]:
    """The accuracy lines under a team size's table (or of the whole suite)."""
    d = a["direct_rot_err_rad"]
    lines = [f"   direct relative rotation error, overlapping pairs (overlap >= {OVERLAP_MIN}): median "
             f"{d['median']:.4f} rad, p90 {d['p90']:.4f} rad, n={d['n']} (target < 0.05 rad)"]
    lines.append(f"   {'ego-motion per robot':<22}{'RPE trans %':>12}{'RPE rot deg':>12}{'end drift %':>12}"
                 f"{'path m':>9}{'steps':>7}   (targets: < {EGO_RPE_TRANS_MAX_PCT:g} %, "
                 f"< {EGO_RPE_ROT_MAX_DEG:g} deg median)")
    for r, e in a["ego_per_robot"].items():
        lines.append(f"   {r:<22}{e['rpe_trans_pct']:>12.2f}{e['rpe_rot_deg_median']:>12.3f}"
                     f"{e['end_drift_pct']:>12.2f}{e['path_m']:>9.2f}{e['n_steps']:>7d}   {_ego_verdict(e)}")
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


def latency_rows(report: dict[str, Any]) -> list[dict[str, Any]]:
    """A ``cerpe bench --out`` report as latency rows ``n_robots, stage, seconds``: each stage's mean per
    robot-step times the team size, i.e. per team step (what the paper's communication figure stacks)."""
    return [{"n_robots": int(r["n_robots"]), "stage": st, "seconds": float(v["mean"]) * int(r["n_robots"]) / 1000}
            for r in report.get("results", []) for st, v in r.get("stage_ms", {}).items()]


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
        lines.append(f"   {'stage (per robot-step)':<24}{'median ms':>10}{'p90 ms':>10}{'mean ms':>10}"
                     f"{'CPU med':>10}{'CPU p90':>10}{'CPU mean':>10}")
        cpu = r.get("stage_cpu_ms", {})
        for s, v in r["stage_ms"].items():
            c = cpu.get(s, {"median": float("nan"), "p90": float("nan"), "mean": float("nan")})
            lines.append(f"   {s:<24}{v['median']:>10.1f}{v['p90']:>10.1f}{v['mean']:>10.1f}"
                         f"{c['median']:>10.1f}{c['p90']:>10.1f}{c['mean']:>10.1f}")
            sn = r.get("sensor_ms")
            if s == "scale" and sn is not None and sn["mean"] > 0:
                lines.append(f"   {'  sensor':<24}{sn['median']:>10.1f}{sn['p90']:>10.1f}{sn['mean']:>10.1f}")
            if s == "backbone":  # the backbone's own profile of its pass, by part (wall; steps with a pass)
                for part, pv in r.get("backbone_pass_ms", {}).items():
                    if part == "total":
                        continue
                    lines.append(f"   {'  ' + part:<24}{pv['median']:>10.1f}{pv['p90']:>10.1f}{pv['mean']:>10.1f}")
        v, c = r["robot_step_ms"], r.get("robot_step_cpu_ms", r["robot_step_ms"])
        sn = r.get("sensor_ms") or {"mean": 0.0}
        label = "robot's work" if sn["mean"] > 0 else "all stages"
        lines.append(f"   {label:<24}{v['median']:>10.1f}{v['p90']:>10.1f}{v['mean']:>10.1f}"
                     f"{c['median']:>10.1f}{c['p90']:>10.1f}{c['mean']:>10.1f}")
        if sn["mean"] > 0:
            w = r["robot_step_with_sensor_ms"]
            lines.append(f"   {'  with the sensor':<24}{w['median']:>10.1f}{w['p90']:>10.1f}{w['mean']:>10.1f}"
                         "   (all stages: the depth a sensor hands over with the frame, read or simulated here)")
        g, gc = r.get("gate_score_ms"), r.get("gate_score_cpu_ms")
        if g is not None:
            lines.append(f"   {'  gate scoring (in gate)':<24}{g['median']:>10.3f}{g['p90']:>10.3f}{g['mean']:>10.3f}"
                         f"{gc['median']:>10.3f}{gc['p90']:>10.3f}{gc['mean']:>10.3f}")
        rt = r.get("robot_target_ms")
        if rt is not None:
            ok = v["median"] <= rt and v["p90"] <= ROBOT_TARGET_P90_MS
            lines.append(f"   robot step targets: median <= {rt:.0f} ms, p90 <= {ROBOT_TARGET_P90_MS:.0f} ms: "
                         f"{'met' if ok else 'NOT met'} (wall)")
        if "process_cpu_ms_per_robot_step" in r:
            lines.append(f"   process CPU per robot-step (every thread: workers', OpenCV's): "
                         f"{r['process_cpu_ms_per_robot_step']:.1f} ms")
        reg = r.get("registration")
        if reg:
            ls, lm = reg["late_steps"], reg["late_ms"]
            lines.append(f"   registration apart from the step: {int(reg['submitted'])} jobs, {reg['landed']} landed "
                         f"({reg['landed_late']} after their step; late steps median {ls['median']:.0f}, p90 "
                         f"{ls['p90']:.0f}; submit-to-landing median {lm['median']:.0f} ms, p90 {lm['p90']:.0f} ms), "
                         f"{int(reg['dropped'])} dropped, {int(reg['failed'])} failed, {int(reg['lost'])} lost, "
                         f"{int(reg['restarts'])} worker restarts, {int(reg['unlanded_at_end'])} not landed at the end; "
                         f"worker CPU {reg['worker_cpu_ms_per_robot_step']:.1f} ms per robot-step")
        lines.append(f"   {'bytes per robot-step':<24}{'median':>10}{'p90':>10}{'mean':>10}")
        for k, v in r["bytes_per_robot_step"].items():
            lines.append(f"   {k:<24}{v['median']:>10.0f}{v['p90']:>10.0f}{v['mean']:>10.0f}")
        c = r.get("cross") or {}
        if any(k != "gated_pairs" for k in c):
            lines.append(f"   cross-robot registration (all steps): {c['gated_pairs']} gated pairs, "
                         f"{c.get('cross-registered', 0)} collaborator views registered, "
                         f"{c.get('cross-none', 0)} not; learned matcher for {c.get('cross-learned', 0)} views "
                         f"({c.get('cross-learned-pairs', 0)} image pairs)")
        lines += format_accuracy(r["accuracy"])
    lines.append(f"descriptor: {descriptor_info['dim']} values; frame bytes " +
                 ", ".join(f"{k} {v}" for k, v in descriptor_info["wire_bytes"].items()))
    return "\n".join(lines)


def format_sweep(results: list[dict[str, Any]]) -> str:
    """One line per team size: a robot's step (wall and CPU), bytes, gate scoring and lateness, and the
    growth of the step from the smallest team (target: at most :data:`TEAM_GROWTH_MAX` times)."""
    base = results[0]
    lines = [f"== team sizes (per robot-step; growth: median wall against the {base['n_robots']}-robot team)",
             f"   {'robots':>6}{'wall med':>10}{'wall p90':>10}{'CPU med':>9}{'CPU p90':>9}{'growth':>8}"
             f"{'bytes':>9}{'score us':>10}{'late med':>9}{'late p90':>9}"]
    for r in results:
        v, c = r["robot_step_ms"], r.get("robot_step_cpu_ms", r["robot_step_ms"])
        growth = v["median"] / base["robot_step_ms"]["median"]
        reg = r.get("registration") or {}
        late = reg.get("late_steps", {"median": float("nan"), "p90": float("nan")})
        sc = r.get("gate_score_cpu_ms", {"median": float("nan")})
        lines.append(f"   {r['n_robots']:>6}{v['median']:>10.1f}{v['p90']:>10.1f}{c['median']:>9.1f}{c['p90']:>9.1f}"
                     f"{growth:>8.2f}{r['bytes_per_robot_step']['total']['mean']:>9.0f}{1000 * sc['median']:>10.0f}"
                     f"{late['median']:>9.0f}{late['p90']:>9.0f}")
    top = results[-1]["robot_step_ms"]["median"] / base["robot_step_ms"]["median"]
    lines.append(f"   {results[-1]['n_robots']} robots against {base['n_robots']}: {top:.2f}x "
                 f"(target <= {TEAM_GROWTH_MAX}x: {'met' if top <= TEAM_GROWTH_MAX else 'NOT met'})")
    return "\n".join(lines)
