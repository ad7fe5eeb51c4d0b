"""DEVELOPMENT tool: how far apart are right and wrong direct estimates, and what would verification do?

Reads CERPE run folders where every direct estimate was recorded (the ``dir_*`` columns
of ``steps.csv``, whatever verification said; or, in runs without them, ``est_*`` of
runs made with ``anchors.verify=false``) and prints:

1. ``pairs``: for every direct estimate and every earlier one of the same ordered
   pair at most ``--max-gap`` steps before, the disagreement of the new one with the
   old one propagated to it (rotation rad, translation m), split by ground truth:
   both right (e_rot < 0.1 rad) or at least one wrong (e_rot > 0.3 rad); with the
   rotation per step since and translation per metre travelled.
2. ``replay``: :class:`cerpe.algorithm.anchors.PairAnchors` fed with those direct
   estimates in order (the anchor state needs nothing else: odometry and the gate
   do not depend on it), what each step would report, and: estimates reported,
   their mean / median e_rot, success, rejections, and the longest a > 0.3 rad
   wrong estimate is carried by propagation.
3. ``report``: the development report's row (``cerpe dev``'s figures) of each run
   replayed under its own ``run.json`` configuration tree with the ``--set`` changes
   (exact for the switch back end with the ``gate`` request policy, except that
   second registrations of one step are not recorded and so verify nothing).

``--set`` takes dotted keys of the configuration tree (:mod:`cerpe.method_config`; the replay
reads ``anchors.*`` and ``backend.propagate``); ``pairs`` and ``replay`` start from the defaults,
``report`` from each run's own tree. Usage::

    python -m lab.anchor_replay --record MANIFEST RUN   # cerpe run with anchors.verify=false
    python -m lab.anchor_replay RUN [RUN...] [--max-gap 10] [--set anchors.rot_tol_rad=0.1 ...]
    python -m lab.anchor_replay build/dev/runs/*/cerpe --what report --set anchors.report_unverified=false

Development data only (synthetic seeds other than 0, ``../shared/data``).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd

from cerpe import knobs
from cerpe.algorithm import AlgorithmConfig
from cerpe.algorithm.anchors import NOT_REPORTED, Anchor, PairAnchors, disagreement
from cerpe.geometry import e_rot, se3_from_tq_xyzw
from cerpe.method_config import CerpeConfig
from cerpe.pipeline.run import RunError, parse_sets

from .runconf import RunConfigError, run_tree

POSE = ("tx", "ty", "tz", "qx", "qy", "qz", "qw")
RIGHT, WRONG = 0.1, 0.3


def _poses(df: pd.DataFrame, prefix: str) -> np.ndarray:
    v = df[[f"{prefix}_{n}" for n in POSE]].to_numpy(float)
    out = np.full((len(v), 4, 4), np.nan)
    for k, row in enumerate(v):
        if np.all(np.isfinite(row)):
            out[k] = se3_from_tq_xyzw(row[:3], row[3:])
    return out


def load(run: Path):
    """Yield ``(encounter, ego, other, rows, metric)`` with per-step direct T, gt T, both odometries and odometers.

    The direct estimate is ``dir_*`` (recorded whatever verification said of it) where the run has
    those columns, else ``est_*`` of the rows whose source is ``direct`` (runs with ``anchors.verify=false``).
    """
    meta = json.loads((run / "run.json").read_text())
    metric = bool(meta.get("metric_scale", True))
    for enc in sorted(p for p in run.iterdir() if (p / "DONE.json").exists()):
        steps = pd.read_csv(enc / "steps.csv")
        robots = pd.read_csv(enc / "robots.csv").sort_values("step")
        odo, X = {}, {}
        for rid, g in robots.groupby("robot"):
            P = _poses(g, "odom")
            X[rid] = dict(zip(g["step"], P))
            d = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1))]
            odo[rid] = dict(zip(g["step"], d))
        has_dir = "dir_tx" in steps.columns
        for (ego, other), g in steps.groupby(["ego", "other"]):
            g = g.sort_values("step")
            rows = []
            D = _poses(g, "dir" if has_dir else "est")
            for (_, r), T, G in zip(g.iterrows(), D, _poses(g, "gt")):
                t = int(r["step"])
                if str(r.get("reason", "")).startswith("anchor-not-stored"):
                    direct = False
                elif has_dir:
                    direct = bool(np.all(np.isfinite(T)))
                else:
                    direct = r["source"] == "direct"
                rows.append(dict(step=t, direct=direct, T=T if direct else None, gt=G, X_i=X[ego][t],
                                 X_j=X[other][t], odo_i=odo[ego][t], odo_j=odo[other][t],
                                 inliers=int(r.get("direct_inliers", -1)), index=r.name))
            yield enc.name, ego, other, rows, metric


def err(T, G) -> float:
    return float(e_rot(T, G)) if T is not None and np.all(np.isfinite(G)) else float("nan")


def anchor(r, metric) -> Anchor:
    return Anchor(r["step"], r["T"], r["X_i"], r["X_j"], r["odo_i"], r["odo_j"], metric, r["inliers"])


def _cols(prefix: str, T) -> list[float]:
    from cerpe.geometry import se3_to_tq_xyzw

    if T is None or not np.all(np.isfinite(T)):
        return [np.nan] * 7
    t, q = se3_to_tq_xyzw(T)
    return [*t, *q]


def replay_pair(rows, metric: bool, cfg: AlgorithmConfig):
    """Yield ``(row, verdict, reported T or None, its anchor step or -1, source, candidates dropped)`` per
    step of one ordered pair, as the switch back end (``RobotAgent._relative``) would decide under ``cfg``
    (its ``anchors`` group and ``backend.propagate``)."""
    conf = cfg.anchors
    pa = PairAnchors(conf)
    for r in rows:
        t, rep, verdict, src_step, source, dropped = r["step"], None, "", -1, "none", 0
        if conf.verify:
            pa.track(t, r["X_i"], r["X_j"])
        if r["direct"]:
            est = anchor(r, metric)
            if conf.verify:
                check = pa.offer(est)
                verdict, dropped = check.verdict, len(check.dropped)
            else:
                pa.anchor, verdict = est, "unchecked"
            if verdict not in NOT_REPORTED and (verdict != "unverified" or conf.report_unverified):
                rep, src_step, source = r["T"], t, "direct"
        if rep is None and cfg.backend.propagate:
            a, _ = pa.carried(t)
            if a is not None:
                rep, src_step, source = a.propagated(r["X_i"], r["X_j"]), a.step, "propagated"
        yield r, verdict, rep, src_step, source, dropped


def replay_report(run_path: Path, cfg: AlgorithmConfig, name: str | None = None) -> tuple[dict, pd.DataFrame]:
    """The dev report's row (:func:`cerpe.pipeline.devreport.method_row`) of ``run_path`` with its
    anchors replayed under ``cfg`` (e.g. :func:`lab.runconf.run_tree`; switch back end, ``policy.mode`` gate:
    the gate and the passes do not depend on the anchors, so only the verdicts and what is reported
    change; second registrations of one step are not recorded, so they verify nothing here). Also
    the replayed rows."""
    from cerpe.pipeline.devreport import method_row
    from cerpe.pipeline.evaluate import load_run

    run = load_run(run_path, allow_partial=True)
    steps = run.steps.copy()
    steps[["source", "anchor_verdict"]] = steps[["source", "anchor_verdict"]].astype(object)  # all NaN in some runs
    est_cols = [f"est_{n}" for n in POSE]
    dropped = 0
    for enc, ego, other, rows, metric in load(run_path):
        sel = steps.index[(steps.encounter.astype(str) == enc) & (steps.ego == ego) & (steps.other == other)]
        by_step = dict(zip(steps.loc[sel, "step"].astype(int), sel))
        for r, verdict, rep, src_step, source, n_dropped in replay_pair(rows, metric, cfg):
            dropped += n_dropped
            i = by_step[r["step"]]
            steps.loc[i, est_cols] = _cols("est", rep)
            steps.loc[i, ["source", "anchor_step", "anchor_verdict"]] = [source, src_step, verdict]
    run.steps = steps
    row = method_row(run, name)
    row["anchors_rejected"] = int((steps["anchor_verdict"] == "rejected").sum()) + dropped  # not the recorded ones
    row["anchors_replaced"] = int((steps["anchor_verdict"] == "replaced").sum())
    return row, steps


def pair_table(runs, max_gap: int) -> pd.DataFrame:
    out = []
    for run in runs:
        for enc, ego, other, rows, metric in load(run):
            direct = [r for r in rows if r["direct"]]
            for b, rb in enumerate(direct):
                for ra in direct[:b]:
                    k = rb["step"] - ra["step"]
                    if k > max_gap:
                        continue
                    rot, trans = disagreement(anchor(ra, metric), anchor(rb, metric))
                    ea, eb = err(ra["T"], ra["gt"]), err(rb["T"], rb["gt"])
                    out.append(dict(run=run.name, enc=enc, ego=ego, other=other, a=ra["step"], b=rb["step"], k=k,
                                    rot=rot, trans=trans if metric else np.nan,
                                    travelled=(rb["odo_i"] - ra["odo_i"]) + (rb["odo_j"] - ra["odo_j"]),
                                    dist=float(np.linalg.norm(rb["T"][:3, 3])), err_a=ea, err_b=eb))
    return pd.DataFrame(out)


def replay(runs, cfg: AlgorithmConfig) -> pd.DataFrame:
    out = []
    for run in runs:
        for enc, ego, other, rows, metric in load(run):
            carried_from: dict[int, int] = {}
            for r, verdict, rep, src_step, _, _ in replay_pair(rows, metric, cfg):
                t = r["step"]
                e = err(rep, r["gt"])
                ep = float(np.linalg.norm(rep[:3, 3] - r["gt"][:3, 3])) if rep is not None else np.nan
                if src_step >= 0 and src_step != t and e > WRONG:
                    carried_from[src_step] = carried_from.get(src_step, 0) + 1
                out.append(dict(run=run.name, enc=enc, ego=ego, other=other, step=t, direct=r["direct"],
                                verdict=verdict, reported=rep is not None, e_rot=e, e_pos=ep if metric else np.nan,
                                direct_err=err(r["T"], r["gt"]) if r["direct"] else np.nan,
                                wrong_carried=max(carried_from.values(), default=0)))
    return pd.DataFrame(out)


def record(manifest: Path, out: Path) -> None:
    """``cerpe run MANIFEST --method cerpe --set anchors.verify=false``: every direct estimate kept."""
    from cerpe.pipeline.run import run_method

    print("run folder:", run_method(manifest, "cerpe", out, sets={"anchors.verify": False}, progress=False))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--record", action="store_true", help="RUNS = MANIFEST OUT: write a run to replay")
    ap.add_argument("--max-gap", type=int, default=10)
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="dotted keys of the configuration tree, e.g. anchors.rot_tol_rad=0.1")
    ap.add_argument("--what", choices=["pairs", "replay", "both", "report"], default="both")
    a = ap.parse_args()
    if a.record:
        if len(a.runs) != 2:
            raise SystemExit("anchor_replay --record: expected MANIFEST OUT")
        return record(*a.runs)
    try:
        changes = parse_sets(a.set)
        cfg = CerpeConfig().override(changes)
        confs = [run_tree(run, changes) for run in a.runs] if a.what == "report" else []
    except (RunError, RunConfigError, knobs.KnobError) as exc:
        raise SystemExit(f"anchor_replay: {exc}") from None
    pd.set_option("display.width", 200)
    if a.what == "report":
        rows = [replay_report(run, conf, run.parent.name)[0] for run, conf in zip(a.runs, confs)]
        print(pd.DataFrame(rows).round(3).to_string())
        return None
    if a.what in ("pairs", "both"):
        P = pair_table(a.runs, a.max_gap)
        P["cls"] = np.where((P.err_a < RIGHT) & (P.err_b < RIGHT), "right",
                            np.where((P.err_a > WRONG) | (P.err_b > WRONG), "wrong", "between"))
        P["rot_per_step"] = P.rot / P.k
        P["trans_per_m"] = P.trans / np.maximum(P.travelled, 1e-3)
        q = [0.5, 0.9, 0.95, 0.99, 1.0]
        for col in ("rot", "rot_per_step", "trans", "trans_per_m"):
            print(f"--- {col} quantiles {q} (count) by run and class")
            print(P.groupby(["run", "cls"])[col].quantile(q).unstack().round(3)
                  .join(P.groupby(["run", "cls"])[col].count().rename("n")))
        R = P[P.cls == "right"]
        print("--- right pairs: rot quantiles by gap k (all runs)")
        print(R.groupby(np.minimum(R.k, 6)).rot.quantile([0.9, 0.99, 1.0]).unstack().round(3)
              .join(R.groupby(np.minimum(R.k, 6)).rot.count().rename("n")))
        print("--- wrong pairs: fraction with rot below x")
        wrong = P[P.cls == "wrong"]
        for x in (0.1, 0.15, 0.2, 0.3):
            print(x, (wrong.rot < x).groupby(wrong.run).mean().round(3).to_dict())
    if a.what in ("replay", "both"):
        R = replay(a.runs, cfg)
        g = R.groupby("run")
        summary = pd.DataFrame({
            "steps": g.size(),
            "direct": g.direct.sum(),
            "direct_wrong": g.direct_err.apply(lambda s: int((s > WRONG).sum())),
            "rejected": g.verdict.apply(lambda s: int((s == "rejected").sum())),
            "rejected_right": g.apply(lambda d: int(((d.verdict == "rejected") & (d.direct_err < RIGHT)).sum())),
            "kept_wrong": g.apply(lambda d: int((d.verdict.isin(["verified", "accepted", "replaced", "unchecked"])
                                                 & (d.direct_err > WRONG)).sum())),
            "unverified": g.verdict.apply(lambda s: int((s == "unverified").sum())),
            "replaced": g.verdict.apply(lambda s: int((s == "replaced").sum())),
            "success_pct": 100 * g.reported.mean(),
            "e_rot_mean": g.e_rot.mean(),
            "e_rot_median": g.e_rot.median(),
            "e_pos_mean": g.e_pos.mean(),
            "e_pos_median": g.e_pos.median(),
            "reported_wrong": g.e_rot.apply(lambda s: int((s > WRONG).sum())),
            "max_wrong_carried": R.groupby(["run", "enc", "ego", "other"]).wrong_carried.max().groupby("run").max(),
        })
        print("--- replay with", {"anchors": knobs.as_dict(cfg.anchors), "backend.propagate": cfg.backend.propagate})
        print(summary.round(3).to_string())


if __name__ == "__main__":
    main()
