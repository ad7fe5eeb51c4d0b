"""Calibrate the pose graph's noise models (``cerpe-graph``) on development data only.

Usage::

    cerpe dev --methods cerpe cerpe-wo-em cerpe-graph      # development runs (real dev sets, seed >= 1)
    python -m lab.graph_calibrate [--runs build/dev/runs] [--stat median] [--grid] [--oracle]
                                  [--out build/dev/graph_calibration.json]

1. Direct estimates (every ``dir_*`` of the runs, accepted or rejected) against ground truth,
   per depth kind (the ``rel_sigma`` its depth source reports: 0 for a depth sensor, 0.094 for
   the mono-sim prior; :func:`lab.graphdev.fit_direct_kinds`): per-axis rotation
   sigma = median rotation error / 1.5382 (the median of a 3-D isotropic Gaussian's norm),
   across the line between the cameras median / 1.1774 (Rayleigh), along it median |error| /
   0.6745, relative to the distance; then floors and gains on ``rel`` in quadrature over the
   kinds (``direct_*``, ``direct_depth_*``), and the observed against the predicted sigmas per
   kind; samples more than 0.5 rad off are left out (gross errors are the kernel's job). Estimates
   without a ``rel`` (no metric depth) give ``direct_depth_rel_unknown`` (rotation, across) and their own
   along-line gain ``direct_depth_along_unknown``; the along-line gains per kind are also given on top
   of the shipped floors (``graphdev.along_gains_on_floors``: the ones ``GraphModel`` can take as is).
2. Odometry increments of every robot against ground truth (synthetic sets and real sets
   with trajectories), one step and 5 / 10 / 20 steps: per-step and per-metre sigmas from
   single steps (least squares on squared errors, own-odometry failures and jumps above
   ``odo_jump_rad`` per step left out: the graph models them apart), then the
   ratio of the observed to the modelled RMS error over longer windows (drift correlated
   over steps makes it > 1).
3. With ``--grid``: replay the graph (:func:`lab.graphdev.replay_run`), from the noise
   models fitted in 1 and 2 (not the defaults), on every
   ``cerpe-graph`` run with multipliers of both models and Cauchy kernel widths, and print e_pos,
   e_rot, success and the calibration ratio per set against CERPE and CERPE w/o EM.
4. With ``--oracle``: replay with the direct translations corrected from ground truth
   (:data:`lab.graphdev.ORACLES`: one distance scale per pair, no error along the line
   between the cameras, exact translations): what a fix of the direct estimates' scale could give.

Refuses run folders of the paper-default suite (seed 0: test data).
"""
from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from cerpe.algorithm.graph_model import GRAPH_MODEL, GraphModel, odometry_noise_var, sensor_like
from cerpe.pipeline.devreport import GRAPH_BOUND
from cerpe.pipeline.evaluate import frame_errors, load_run, summarise

from .graphdev import (
    MAXWELL_MEDIAN,
    ORACLES,
    GraphDevError,
    along_gains_on_floors,
    depth_rel_sigma,
    dev_sets,
    direct_samples,
    fit_direct_kinds,
    odometry_samples,
    replay_run,
)

ROOT = Path(__file__).resolve().parents[1]


def _sets(runs: Path) -> list[Path]:
    try:
        return dev_sets(runs)
    except GraphDevError as exc:
        raise SystemExit(str(exc)) from None


def direct_table(sets: list[Path]) -> pd.DataFrame:
    """Every recorded direct estimate of the sets' ``cerpe-graph`` runs against ground truth
    (:func:`direct_samples`), with its set and the ``rel`` sigma of its depth source (NaN: none)."""
    S = []
    for d in sets:
        run = load_run(d / "cerpe-graph")
        rel = depth_rel_sigma(run.meta)
        S.append(direct_samples(run.steps).assign(set=d.name, rel=np.nan if rel is None else rel))
    return pd.concat(S, ignore_index=True)


def fit_direct(sets: list[Path], stat: str = "median") -> dict:
    S = direct_table(sets)
    try:
        fit = fit_direct_kinds(S, stat=stat)
    except GraphDevError as exc:
        raise SystemExit(str(exc)) from None
    per_set = S.groupby("set").agg(n=("rot_err_rad", "size"), rel=("rel", "first"), rot_median=("rot_err_rad", "median"),
                                   along_median=("along_m", lambda v: float(np.median(np.abs(v)))),
                                   perp_median=("perp_m", "median"), dist_median=("dist_m", "median"),
                                   gross_pct=("rot_err_rad", lambda v: 100 * float(np.mean(v >= 0.5))))
    return {**fit, "per_set": per_set.reset_index().to_dict("records")}


def fit_odometry(sets: list[Path]) -> dict:
    """Odometry noise from every set (one model: per-depth-kind fits were measured worse, see commit
    9b719d3; the shipped model scales it by ``odo_sensor_scale`` on sensor-like depth), and the ratio of
    observed to modelled error over longer windows per depth kind ``rel``, under the fit and under the
    shipped model (``shipped_*``, with that scale)."""
    from cerpe.pipeline.setting import load_manifest_setting

    rows = []
    for d in sets:
        run = load_run(d / "cerpe-graph")
        rel = depth_rel_sigma(run.meta)
        setting = load_manifest_setting(Path(run.meta["manifest"]))
        for enc in setting.encounters:
            R = run.robots[run.robots["encounter"] == enc.name]
            for r in enc.robots:
                if r.T_world_cam is None or not np.all(np.isfinite(r.T_world_cam)):
                    continue
                for s in odometry_samples(R[R["robot"] == r.robot_id], r.T_world_cam, jump_rad=GRAPH_MODEL.odo_jump_rad):
                    rows.append({**s, "set": d.name, "rel": -1.0 if rel is None else rel})
    O = pd.DataFrame(rows)
    one = O[(O["window"] == 1) & ~O["failed"]]
    # per-axis variances: |e|^2 / 3 = s0^2 + (s_m d)^2 + (s_rad a)^2 (non-negative least squares)
    from scipy.optimize import nnls

    A = np.stack([np.ones(len(one)), one["dist_m"] ** 2, one["angle_rad"] ** 2], 1)
    cr, _ = nnls(A, one["rot_err_rad"].to_numpy() ** 2 / 3)
    ct, _ = nnls(A[:, :2], one["trans_err_m"].to_numpy() ** 2 / 3)
    fit = {"odo_rot_per_step": float(np.sqrt(cr[0])), "odo_rot_per_m": float(np.sqrt(cr[1])),
           "odo_rot_per_rad": float(np.sqrt(cr[2])), "odo_trans_per_step": float(np.sqrt(ct[0])),
           "odo_trans_per_m": float(np.sqrt(ct[1]))}
    growth = []
    fitted = dataclasses.replace(GRAPH_MODEL, **fit)
    for (rel, w), g in O[~O["failed"]].groupby(["rel", "window"]):
        row = {"rel": float(rel), "window": int(w), "n": int(len(g)),
               "trans_median_m": float(g["trans_err_m"].median()), "trans_rms_m": float(np.sqrt(np.mean(g["trans_err_m"] ** 2)))}
        sensor = sensor_like(GRAPH_MODEL, None if rel < 0 else float(rel))
        for tag, c, sens in (("", fitted, False), ("shipped_", GRAPH_MODEL, sensor)):  # the fit; the shipped model
            row.update({f"{tag}{k}": v for k, v in _odo_ratios(g, w, c, sens).items()})
        growth.append(row)
    fails = O[(O["window"] == 1)]
    return {**fit, "n_steps": int(len(one)), "failed_steps": int(fails["failed"].sum()), "growth": growth}


def _odo_ratios(g: pd.DataFrame, w: int, conf: GraphModel, sensor: bool) -> dict:
    """Observed over modelled odometry error of ``w``-step windows ``g`` under ``conf``'s odometry model
    (``sensor``: with its sensor-like scale), the motion of a window spread evenly over its steps."""
    var_r, var_t = odometry_noise_var(conf, w, g["dist_m"].to_numpy(), g["angle_rad"].to_numpy(), sensor)
    return {"rot_ratio": float(np.sqrt(np.mean(g["rot_err_rad"] ** 2) / np.mean(3 * var_r))),
            "trans_ratio": float(np.sqrt(np.mean(g["trans_err_m"] ** 2) / np.mean(3 * var_t))),
            "trans_median_ratio": float(np.median(g["trans_err_m"] / np.sqrt(3 * var_t)) / (MAXWELL_MEDIAN / np.sqrt(3)))}


def scaled(conf: GraphModel, odo: float, direct: float, k: float, along: float | None = None) -> GraphModel:
    f = {n: getattr(conf, n) * odo for n in ("odo_rot_per_step", "odo_rot_per_m", "odo_rot_per_rad",
                                             "odo_trans_per_step", "odo_trans_per_m")}
    f.update({n: getattr(conf, n) * direct for n in ("direct_rot_rad", "direct_trans_m", "direct_trans_rel",
                                                     "direct_depth_rot", "direct_depth_across", "direct_depth_along",
                                                     "direct_depth_along_unknown")})
    if along is not None:
        f["direct_along_factor"] = along
    return dataclasses.replace(conf, **f, kernel_k=k)


def summary(steps: pd.DataFrame, every: int) -> dict:
    f = frame_errors(steps, True, every).assign(g="x")
    s = summarise(f, ["g"]).iloc[0]
    out = {"e_pos_m": float(s["e_pos_m"]), "e_rot_rad": float(s["e_rot_rad"]), "success_pct": float(s["success_pct"])}
    ok = f[f["success"]]
    if "sigma_pos_m" in ok and np.isfinite(ok["sigma_pos_m"]).any():
        out["pos_ratio"] = float(np.sqrt(np.nanmean(ok["e_pos_m"] ** 2) / np.nanmean(ok["sigma_pos_m"] ** 2)))
        # median error over predicted sigma, 1 when calibrated (a 3-D Gaussian's median norm over its RMS)
        out["pos_med_ratio"] = float(np.nanmedian(ok["e_pos_m"] / ok["sigma_pos_m"]) / (MAXWELL_MEDIAN / np.sqrt(3)))
    return out


def grid(sets: list[Path], base: GraphModel, odo: list[float], direct: list[float], ks: list[float],
         alongs: list[float]) -> pd.DataFrame:
    rows = []
    ref = {}
    for d in sets:
        for m in ("cerpe", "cerpe-wo-em"):
            if (d / m / "run.json").is_file():
                r = load_run(d / m)
                ref[(d.name, m)] = summary(r.steps, r.every)
    for o, di, k, al in itertools.product(odo, direct, ks, alongs):
        conf = scaled(base, o, di, k, al)
        for d in sets:
            run = load_run(d / "cerpe-graph")
            s = summary(replay_run(d / "cerpe-graph", conf), run.every)
            c, w = ref.get((d.name, "cerpe"), {}), ref.get((d.name, "cerpe-wo-em"), {})
            bound = GRAPH_BOUND * c.get("e_pos_m", np.nan)
            rows.append({"odo_x": o, "direct_x": di, "kernel_k": k, "along": al, "set": d.name, **s,
                         "cerpe_e_pos": c.get("e_pos_m"), "woem_e_pos": w.get("e_pos_m"), "bound_e_pos": bound,
                         "cerpe_e_rot": c.get("e_rot_rad"), "cerpe_success": c.get("success_pct"),
                         "pos_ok": bool(s["e_pos_m"] <= bound), "rot_ok": bool(s["e_rot_rad"] <= c.get("e_rot_rad", np.inf)),
                         "succ_ok": bool(s["success_pct"] >= c.get("success_pct", 0))})
    return pd.DataFrame(rows)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=Path, default=ROOT / "build" / "dev" / "runs")
    p.add_argument("--grid", action="store_true",
                   help="replay the graph with the noise models FITTED above (not GRAPH_MODEL's values) times "
                        "--odo / --direct, and kernel widths --k: a row at 1 1 1 is the fit, not the shipped graph")
    p.add_argument("--odo", type=float, nargs="+", default=[1.0, 2.0, 4.0])
    p.add_argument("--direct", type=float, nargs="+", default=[1.0, 2.0])
    p.add_argument("--k", type=float, nargs="+", default=[1.0, 2.0])
    p.add_argument("--along", type=float, nargs="+", default=[1.0], help="direct_along_factor values")
    p.add_argument("--stat", default="median", choices=("median", "trimmed", "rms"),
                   help="direct estimates' sigmas from median errors (robust) or RMS errors (the calibration figure's)")
    p.add_argument("--oracle", action="store_true",
                   help="replay with the direct translations corrected from ground truth (graphdev.ORACLES): "
                        "upper bounds of a scale fix, e_pos per set")
    p.add_argument("--out", type=Path, default=None, help="write the fit (and grid) as JSON here")
    args = p.parse_args()
    sets = _sets(args.runs)
    if not sets:
        raise SystemExit(f"{args.runs}: no cerpe-graph development runs (run `cerpe dev --methods cerpe cerpe-wo-em "
                         f"cerpe-graph` first)")
    print("sets:", ", ".join(d.name for d in sets))
    direct = fit_direct(sets, args.stat)
    print("direct estimates:", json.dumps({k: v for k, v in direct.items() if k not in ("per_set", "kinds")}, indent=1))
    direct["along_gains_on_shipped_floors"] = along_gains_on_floors(direct, GRAPH_MODEL)
    print("along-line gains on the shipped floors (rel: gain; 'unknown': on direct_depth_rel_unknown):",
          json.dumps(direct["along_gains_on_shipped_floors"]))
    print("per depth kind (rel: the depth source's relative scale sigma; observed, the fit's and the defaults' "
          "sigmas; across/along per metre):")
    K, c = pd.DataFrame(direct["kinds"]), GRAPH_MODEL
    K["default_rot"] = np.hypot(c.direct_rot_rad, c.direct_depth_rot * K["rel"])
    K["default_across_rel"] = np.hypot(c.direct_trans_rel, c.direct_depth_across * K["rel"])
    K["default_along_rel"] = np.hypot(c.direct_along_factor * c.direct_trans_rel, c.direct_depth_along * K["rel"])
    with pd.option_context("display.width", 250, "display.max_columns", 30):
        print(K.to_string(index=False, float_format=lambda v: f"{v:.4f}"))
    print(pd.DataFrame(direct["per_set"]).to_string(index=False))
    odo = fit_odometry(sets)
    print("odometry:", json.dumps({k: v for k, v in odo.items() if k != "growth"}, indent=1))
    print(pd.DataFrame(odo["growth"]).to_string(index=False))
    result = {"direct": direct, "odometry": odo, "command": " ".join(sys.argv)}
    if args.grid:
        base = dataclasses.replace(GRAPH_MODEL, **{k: v for k, v in {**direct, **odo}.items()
                                                   if k in GraphModel.__dataclass_fields__})
        print("grid: replays from the fitted noise models above (not the defaults), scaled by --odo / --direct")
        g = grid(sets, base, args.odo, args.direct, args.k, args.along)
        with pd.option_context("display.width", 250, "display.max_columns", 30, "display.max_rows", 500):
            print(g.to_string(index=False, float_format=lambda v: f"{v:.3f}"))
        result["grid"] = g.to_dict("records")
    if args.oracle:
        rows = []
        for d in sets:
            run = load_run(d / "cerpe-graph")
            row = {"set": d.name, "recorded": summary(run.steps, run.every)["e_pos_m"]}
            for name in ORACLES:
                row[name] = summary(replay_run(d / "cerpe-graph", oracle=name), run.every)["e_pos_m"]
            rows.append(row)
        print("e_pos (m) of the graph with direct translations corrected from ground truth:")
        print(pd.DataFrame(rows).to_string(index=False, float_format=lambda v: f"{v:.3f}"))
        result["oracle"] = rows
    if args.out:
        args.out.write_text(json.dumps(result, indent=1, default=float))
        print("written:", args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
