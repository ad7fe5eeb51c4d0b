"""The development tools of the pose graph (lab/graphdev.py, lab/graph_replay.py): replaying recorded
passes gives the runs' estimates back, the noise models' fit recovers known covariances, the oracles,
and a replay judged by `cerpe dev`'s graph checks."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cerpe.algorithm import GRAPH_MODEL
from cerpe.pipeline import evaluate as ev
from lab.graphdev import replay_run
from test_pipeline_graph import POSE, runs  # noqa: F401  (runs: the toy world's cerpe and cerpe-graph runs)


def test_replay_of_the_recorded_pass_gives_the_runs_estimates(runs):
    _, _, _, out = runs
    run = ev.load_run(out["cerpe-graph"])
    rep = replay_run(out["cerpe-graph"], GRAPH_MODEL)  # the toy runs' test double records no tree: its model
    key = ["encounter", "ego", "other", "step"]
    a = run.steps.sort_values(key).reset_index(drop=True)
    b = rep.sort_values(key).reset_index(drop=True)
    assert (a["source"] == b["source"]).all()
    cols = [f"est_{c}" for c in POSE] + ["sigma_pos_m", "sigma_rot_rad"]
    np.testing.assert_allclose(a[cols].to_numpy(float), b[cols].to_numpy(float), atol=1e-6)
    # replaying the paper's CERPE pass (same records) gives the same graph estimates: the pass is the same
    rep2 = replay_run(out["cerpe"], GRAPH_MODEL).sort_values(key).reset_index(drop=True)
    np.testing.assert_allclose(rep2[cols].to_numpy(float), b[cols].to_numpy(float), atol=1e-6)


def test_odometry_samples_mark_a_jump_as_a_failure_for_the_calibration():
    # dev indoor seed 2001: one 1.7 rad odometry jump made the calibration's per-radian rotation sigma 0.5
    from cerpe.geometry import make_se3, se3_to_tq_xyzw, so3_exp
    from lab.graphdev import odometry_samples

    n = 12
    T = np.stack([make_se3(so3_exp(np.array([0.0, 0.02 * t, 0.0])), np.array([0.3 * t, 0.0, 0.0])) for t in range(n)])
    X = T.copy()
    X[6:] = X[6:] @ make_se3(so3_exp(np.array([0.0, 1.7, 0.0])), np.zeros(3))  # the jump at step 6 (never made)
    t_, q_ = se3_to_tq_xyzw(X)
    rows = pd.DataFrame({"step": range(n), "degradations": [""] * n,
                         **{f"odom_{c}": v for c, v in zip(ev.POSE, np.concatenate([t_, q_], 1).T)}})
    plain = list(odometry_samples(rows, T, windows=(1, 3)))
    assert not any(s["failed"] for s in plain)
    marked = list(odometry_samples(rows, T, windows=(1, 3), jump_rad=1.0))
    # windows (a, a + w] holding step 6: a in [6 - w, 5]; they and only they are failures, and only they are wrong
    want = [w >= 1 and 6 - w <= a <= 5 for w in (1, 3) for a in range(n - w)]
    assert [s["failed"] for s in marked] == want
    assert all((s["rot_err_rad"] > 1.0) == f for s, f in zip(marked, want))


def test_direct_noise_fit_recovers_hand_made_covariances_per_depth_kind():
    # direct estimates drawn from direct_cov of a known model for a sensor's (rel 0) and a monocular
    # prior's (rel 0.1) depth, through steps.csv columns and direct_samples: the fit gives the model back,
    # and its per-kind predicted sigmas match the observed ones
    from cerpe.algorithm.graph import DirectEstimate, GraphModel, direct_cov
    from cerpe.geometry import make_se3, random_se3, se3_to_tq_xyzw, so3_exp
    from lab.graphdev import along_gains_on_floors, direct_samples, fit_direct_kinds

    true = GraphModel(direct_rot_rad=0.003, direct_trans_m=0.004, direct_trans_rel=0.006, direct_along_factor=1.0,
                       direct_depth_rot=0.05, direct_depth_across=0.25, direct_depth_along=1.0)
    rng = np.random.default_rng(7)
    parts = []
    for rel, n in ((0.0, 1500), (0.1, 1500), (np.nan, 600)):
        gt, est = [], []
        for _ in range(n):
            G = random_se3(rng, 1.0)
            G[:3, 3] *= rng.uniform(1.0, 12.0) / np.linalg.norm(G[:3, 3])
            C = direct_cov(true if np.isfinite(rel) else
                           dataclasses.replace(true, direct_depth_rel_unknown=0.4, direct_depth_along_unknown=2.5),
                           DirectEstimate(0, G, depth_rel_sigma=None if np.isnan(rel) else rel))
            x = rng.multivariate_normal(np.zeros(6), C)
            gt.append(G)
            est.append(G @ make_se3(so3_exp(x[:3]), x[3:]))
        cols = {}
        for pre, T in (("gt", np.stack(gt)), ("dir", np.stack(est))):
            t, q = se3_to_tq_xyzw(T)
            cols.update({f"{pre}_{c}": v for c, v in zip(POSE, np.concatenate([t, q], 1).T)})
        steps = pd.DataFrame({"encounter": "e", "step": range(n), "ego": "r0", "other": "r1", **cols})
        parts.append(direct_samples(steps).assign(rel=rel))
    fit = fit_direct_kinds(pd.concat(parts, ignore_index=True))
    for name, tol in (("direct_rot_rad", 0.1), ("direct_trans_rel", 0.1), ("direct_depth_rot", 0.15),
                      ("direct_depth_across", 0.1), ("direct_depth_along", 0.1)):
        assert fit[name] == pytest.approx(getattr(true, name), rel=tol), name
    assert fit["direct_along_factor"] == pytest.approx(1.0, abs=0.15)
    # what the no-depth estimates had: rel from their rotation and across errors, their own along gain on it
    assert fit["direct_depth_rel_unknown"] == pytest.approx(0.4, rel=0.15)
    assert fit["direct_depth_along_unknown"] == pytest.approx(2.5, rel=0.15)
    # the gains on other floors: the mono kind's along sigma hypot(0.006, 0.1) per metre on a 0.02 floor
    gains = along_gains_on_floors(fit, dataclasses.replace(true, direct_trans_rel=0.01, direct_along_factor=2.0))
    assert gains[0.1] == pytest.approx(np.sqrt(0.006**2 + 0.1**2 - 0.02**2) / 0.1, rel=0.1)
    assert gains["unknown"] == pytest.approx(np.sqrt(0.006**2 + 1.0**2 - 0.02**2) / true.direct_depth_rel_unknown, rel=0.15)
    assert along_gains_on_floors(fit, dataclasses.replace(true, direct_trans_rel=1.0))[0.1] == 0.0
    for k in fit["kinds"]:
        for q in ("rot", "across_rel", "along_rel"):
            assert k[f"pred_{q}"] == pytest.approx(k[q], rel=0.1), (k["rel"], q)
    # too few estimates of any kind: one clear error
    from lab.graphdev import GraphDevError

    with pytest.raises(GraphDevError, match="depth kind"):
        fit_direct_kinds(parts[0].head(10))


def test_oracles_correct_the_direct_translations_from_ground_truth():
    from lab.graphdev import GraphDevError, oracle_steps

    rng = np.random.default_rng(3)
    gt = rng.normal(size=(6, 3)) * 5.0
    across = np.cross(gt, [0.0, 0.0, 1.0]) * 0.01  # a small error across each line
    d = pd.DataFrame({"gt_tx": gt[:, 0], "gt_ty": gt[:, 1], "gt_tz": gt[:, 2],
                      "dir_tx": (0.9 * gt + across)[:, 0], "dir_ty": (0.9 * gt + across)[:, 1],
                      "dir_tz": (0.9 * gt + across)[:, 2]})
    t = lambda df: df[["dir_tx", "dir_ty", "dir_tz"]].to_numpy()  # noqa: E731
    np.testing.assert_allclose(t(oracle_steps(d, "pair-scale")), gt + across / 0.9, atol=1e-9)  # 10 % short, one scale
    np.testing.assert_allclose(t(oracle_steps(d, "no-along")), gt + across, atol=1e-9)
    np.testing.assert_allclose(t(oracle_steps(d, "exact-translation")), gt)
    with pytest.raises(GraphDevError, match="unknown oracle"):
        oracle_steps(d, "magic")


def test_graph_replay_judges_replays_by_the_dev_checks(runs, tmp_path, monkeypatch):
    """lab/graph_replay.py: at the defaults a replay is judged as `cerpe dev` judges the recorded runs;
    another setting moves the graph's figures; a paper-default run and an unknown key are refused."""
    import json
    import sys

    from cerpe.pipeline.devreport import GRAPH_CHECKS, checks, report
    from lab import graph_replay as script
    from lab.graphdev import GraphDevError, dev_sets

    root, _, _, out = runs
    (tmp_path / "runs").mkdir()
    (tmp_path / "runs" / "toy").symlink_to(root, target_is_directory=True)
    sets = dev_sets(tmp_path / "runs")
    assert [d.name for d in sets] == ["toy"]
    summary, per_set = script.judge(sets, GRAPH_MODEL)
    table, _ = report([("toy", out["cerpe"]), ("toy", out["cerpe-graph"])])
    want = checks(table)
    for c in want.itertuples(index=False):
        if c.check in GRAPH_CHECKS:
            assert summary[c.check] == [int(c.result == "pass"), int(c.result != "n/a")], c.check
    rows = table.set_index("method")
    assert summary["geo_ratio"] == pytest.approx(rows.loc["cerpe-graph", "e_pos_m"] / rows.loc["cerpe", "e_pos_m"])
    assert per_set == [f"toy {summary['geo_ratio']:.3f}"]
    loose, _ = script.judge(sets, dataclasses.replace(GRAPH_MODEL, direct_rot_rad=0.2, direct_trans_rel=0.5))
    assert loose["geo_ratio"] != pytest.approx(summary["geo_ratio"])
    assert script.grid(["kernel_k=1,2", "odo_rot_per_step=0.01"]) == [{"kernel_k": 1, "odo_rot_per_step": 0.01},
                                                                      {"kernel_k": 2, "odo_rot_per_step": 0.01}]
    bad = tmp_path / "paper" / "synthetic-cad" / "cerpe-graph"
    bad.mkdir(parents=True)
    (bad / "run.json").write_text(json.dumps({"manifest": "build/paper-default/synthetic-cad.yaml"}))
    with pytest.raises(GraphDevError, match="paper-default"):
        dev_sets(tmp_path / "paper")
    monkeypatch.setattr(sys, "argv", ["graph_replay", "--runs", str(tmp_path / "runs"), "--set", "kernel_kk=1"])
    with pytest.raises(SystemExit) as exc:
        script.main()
    assert "unknown option(s) 'kernel_kk'; known:" in str(exc.value) and "kernel_k," in str(exc.value)
