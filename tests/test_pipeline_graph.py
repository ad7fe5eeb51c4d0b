"""cerpe-graph through the pipeline: run folder (steps.csv sigmas, the .cov companion of the TUM
file), replay of recorded passes, Table I's extension row, the calibration figure and data."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cerpe import plotting
from cerpe.algorithm import AlgorithmConfig, Team
from cerpe.datasets.formats import read_trajectory
from cerpe.geometry import pose_cov_in_parent, pose_cov_sigmas, se3_from_tq_xyzw
from cerpe.pipeline import evaluate as ev
from cerpe.pipeline import methods, paper, table1
from cerpe.pipeline import run as rp
from cerpe.pipeline.graphdev import replay_run
from cerpe.scene import Setting
from cerpe.tum import parse_tum_cov
from gt_backbone import GTBackbone, OverlapDescriptor, SensorDepthDouble, make_world

POSE = ("tx", "ty", "tz", "qx", "qy", "qz", "qw")


def _gt_prepare(world):
    """``run.prepare_method`` with the ground-truth doubles: CERPE or cerpe-graph on ``world``."""

    def prepare(method, profile, seed, depth=None, every=1, depth_options=None):
        cfg = AlgorithmConfig().override({"scale.min_pixels": 20, "backend.propagate": method != "cerpe-wo-em", "backend.kind": "graph" if method == "cerpe-graph" else "switch"})

        def steps(enc):
            team = Team(world.robot_ids, OverlapDescriptor(world),
                        GTBackbone(world, seed=1, trans_noise=0.02, rot_noise_rad=0.005), SensorDepthDouble(), cfg)
            yield from team.run_encounter(enc)

        return {"cerpe": dataclasses.asdict(cfg)}, steps

    return prepare


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    world = make_world(3, 24, seed=4)
    enc = world.to_encounter("gt")
    enc.overlap = np.full((world.n_steps, 3, 3), 0.5)
    setting = Setting("toy", [enc])
    mp.setattr(rp, "prepare_method", _gt_prepare(world))
    root = tmp_path_factory.mktemp("graphruns")
    m = root / "toy.yaml"
    m.write_text("name: toy\nmetric_depth: sensor\n")  # the replay reads the depth kind (rel_sigma) here
    out = {meth: rp.run_method(m, meth, root / meth, setting=setting, progress=False)
           for meth in ("cerpe", "cerpe-graph")}
    mp.undo()
    return root, m, setting, out


def test_run_folder_has_sigmas_and_covariance_beside_the_tum_file(runs):
    _, _, _, out = runs
    steps = pd.read_csv(out["cerpe-graph"] / "gt" / "steps.csv")
    est = steps[steps["source"] != "none"]
    assert (est["sigma_pos_m"] > 0).all() and (est["sigma_rot_rad"] > 0).all()
    assert steps.loc[steps["source"] == "none", "sigma_pos_m"].isna().all()
    cerpe = pd.read_csv(out["cerpe"] / "gt" / "steps.csv")
    assert {"sigma_pos_m", "sigma_rot_rad", "dir_tx", "direct_inliers"} <= set(cerpe.columns)
    assert cerpe["sigma_pos_m"].isna().all()  # the paper's methods: NaN
    assert not list((out["cerpe"] / "gt" / "poses").glob("*.cov"))
    for cov_file in (out["cerpe-graph"] / "gt" / "poses").glob("*.cov"):
        stamps, cov = parse_tum_cov(cov_file.read_text())
        traj = read_trajectory(cov_file.with_suffix(".tum"), "tum", "estimate")
        np.testing.assert_allclose(stamps, traj.stamps_s)  # line for line with the poses
        ego, other = cov_file.stem.split("__")
        rows = est[(est["ego"] == ego) & (est["other"] == other)].sort_values("step")
        T = se3_from_tq_xyzw(rows[[f"est_{c}" for c in POSE[:3]]].to_numpy(float),
                             rows[[f"est_{c}" for c in POSE[3:]]].to_numpy(float))
        assert len(cov) == len(rows)
        for k in range(len(cov)):  # ROS order, parent frame: symmetric PSD, same traces as the record's sigmas
            np.testing.assert_allclose(cov[k], cov[k].T, atol=1e-12)
            assert np.linalg.eigvalsh(cov[k])[0] > 0
            # rotations keep traces: the position block's trace is sigma_pos_m^2
            assert np.trace(cov[k][:3, :3]) == pytest.approx(rows["sigma_pos_m"].iloc[k] ** 2, rel=1e-6)
            assert np.trace(cov[k][3:, 3:]) == pytest.approx(rows["sigma_rot_rad"].iloc[k] ** 2, rel=1e-6)
        assert T.shape[0] == len(cov)
    with pytest.raises(ValueError, match="line 2"):
        parse_tum_cov("# header\n1.0 2.0 3.0\n")


def test_replay_of_the_recorded_pass_gives_the_runs_estimates(runs):
    _, _, _, out = runs
    run = ev.load_run(out["cerpe-graph"])
    rep = replay_run(out["cerpe-graph"], AlgorithmConfig().graph)
    key = ["encounter", "ego", "other", "step"]
    a = run.steps.sort_values(key).reset_index(drop=True)
    b = rep.sort_values(key).reset_index(drop=True)
    assert (a["source"] == b["source"]).all()
    cols = [f"est_{c}" for c in POSE] + ["sigma_pos_m", "sigma_rot_rad"]
    np.testing.assert_allclose(a[cols].to_numpy(float), b[cols].to_numpy(float), atol=1e-6)
    # replaying the paper's CERPE pass (same records) gives the same graph estimates: the pass is the same
    rep2 = replay_run(out["cerpe"], AlgorithmConfig().graph).sort_values(key).reset_index(drop=True)
    np.testing.assert_allclose(rep2[cols].to_numpy(float), b[cols].to_numpy(float), atol=1e-6)


def test_metric_scale_and_evaluation_of_the_graph_run(runs):
    _, _, _, out = runs
    frames, table = ev.evaluate_runs([out["cerpe"], out["cerpe-graph"]])
    assert table.set_index("method").loc["cerpe-graph", "metric_scale"]
    s = ev.summarise(frames, ["method"]).set_index("method")
    assert s.loc["cerpe-graph", "success_pct"] >= s.loc["cerpe", "success_pct"]
    cal = ev.sigma_calibration(frames)
    assert set(cal["method"]) == {"cerpe-graph"}  # only methods with a covariance
    whole = cal[cal["bin"] < 0].set_index("quantity")
    assert whole.loc["position", "n"] == int(frames[(frames.method == "cerpe-graph") & frames.success].shape[0])


def test_sigma_calibration_known_answer():
    f = pd.DataFrame({"setting": "s", "method": "m", "success": [True] * 4 + [False],
                      "e_pos_m": [1.0, 1.0, 4.0, 4.0, np.nan], "sigma_pos_m": [1.0, 1.0, 2.0, 2.0, np.nan],
                      "e_rot_rad": [0.1] * 4 + [np.nan], "sigma_rot_rad": [0.1] * 4 + [np.nan]})
    t = ev.sigma_calibration(f, n_bins=2)
    pos = t[(t.quantity == "position")].set_index("bin")
    assert pos.loc[-1, "n"] == 4 and pos.loc[-1, "error_rms"] == pytest.approx(np.sqrt(8.5))
    assert pos.loc[0, "ratio"] == pytest.approx(1.0) and pos.loc[1, "ratio"] == pytest.approx(2.0)
    assert pos.loc[1, "within_2sigma_pct"] == pytest.approx(100.0) and pos.loc[-1, "within_2sigma_pct"] == 100.0
    rot = t[(t.quantity == "rotation") & (t.bin == -1)].iloc[0]
    assert rot["ratio"] == pytest.approx(1.0)
    assert ev.sigma_calibration(f.drop(columns=["sigma_pos_m", "sigma_rot_rad"])).empty


def test_table_figures_and_communication_show_the_extension(runs, tmp_path):
    root, m, setting, out = runs
    ctx = paper.PaperContext("fixture", "fixture", "offline", root, tmp_path / "fig", tmp_path / "tab", tmp_path / "nb")
    ctx.settings = [paper.SettingEntry("toy", m, "ok", run_manifest=m, setting=setting)]
    ctx.run_dirs = {("toy", k): v for k, v in out.items()}
    df = table1.main_results(ctx)
    row = df[df.method == "cerpe-graph"].iloc[0]
    assert row.status == "ok" and np.isfinite(row.e_pos_m)
    assert "extension" in methods.METHOD_LABELS["cerpe-graph"] and "cerpe-graph" in methods.EXTENSION_METHODS
    md = table1.main_results_markdown(df)
    assert "our extension, not in the paper" in md
    tex = table1.main_results_latex(df)
    assert tex.count(r"\midrule") == 3  # header, before w/o EM, before the extension
    assert df.attrs["caption"].count("our extension") == 1
    com = paper.communication_data(ctx)
    bt = com["bytes_table"].set_index("scheme")["bytes_per_robot_step"]
    graph_row = [s for s in bt.index if "pose graph" in s]
    assert len(graph_row) == 1 and bt[graph_row[0]] == pytest.approx(bt["CERPE (gated images)"])  # no extra bytes
    assert any("graph update" in q for q in com["summary"]["quantity"])
    plotting.save_figure(plotting.communication_figure(com["bytes_table"], com["gate"], com["latency"]),
                         ctx.figures_dir / "communication_runtime")
    cal = paper.calibration_data(ctx)
    assert set(cal["frames"]) == {"toy"} and set(cal["frames"]["toy"]["method"]) == {"cerpe-graph"}
    fig = plotting.calibration_figure(cal["frames"]["toy"], cal["table"], title="toy")
    paths = plotting.save_figure(fig, ctx.figures_dir / "calibration")
    assert all(p.stat().st_size > 1000 for p in paths)
    frames = paper.frames(ctx)
    plotting.save_figure(plotting.error_analysis_figure(frames, title="toy"), ctx.figures_dir / "error_analysis")
    # a setting without a graph run still gets a (labelled) empty figure
    empty = plotting.calibration_figure(frames[frames.method == "cerpe"], cal["table"].iloc[0:0])
    assert empty is not None


def test_cerpe_graph_is_a_run_method_and_in_the_paper_and_dev_runs():
    from cerpe.pipeline import dev

    assert "cerpe-graph" in methods.CERPE_METHODS and "cerpe-graph" in methods.METHODS
    assert "cerpe-graph" in paper.RUN_METHODS and "cerpe-graph" in dev.METHODS
    assert table1.TABLE_METHODS[-1] == "cerpe-graph" and "05_uncertainty" in paper.NOTEBOOKS
    assert (Path(paper.ROOT) / "notebooks" / "05_uncertainty.ipynb").is_file()


def test_odometry_samples_mark_a_jump_as_a_failure_for_the_calibration():
    # dev indoor seed 2001: one 1.7 rad odometry jump made the calibration's per-radian rotation sigma 0.5
    from cerpe.geometry import make_se3, se3_to_tq_xyzw, so3_exp
    from cerpe.pipeline.graphdev import odometry_samples

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
    from cerpe.algorithm.graph import DirectEstimate, GraphConfig, direct_cov
    from cerpe.geometry import make_se3, random_se3, se3_to_tq_xyzw, so3_exp
    from cerpe.pipeline.graphdev import along_gains_on_floors, direct_samples, fit_direct_kinds

    true = GraphConfig(direct_rot_rad=0.003, direct_trans_m=0.004, direct_trans_rel=0.006, direct_along_factor=1.0,
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
    from cerpe.pipeline.graphdev import GraphDevError

    with pytest.raises(GraphDevError, match="depth kind"):
        fit_direct_kinds(parts[0].head(10))


def test_oracles_correct_the_direct_translations_from_ground_truth():
    from cerpe.pipeline.graphdev import GraphDevError, oracle_steps

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


def test_dev_graph_replay_judges_replays_by_the_dev_checks(runs, tmp_path):
    """scripts/dev_graph_replay.py: at the defaults a replay is judged as `cerpe dev` judges the recorded runs;
    another setting moves the graph's figures; a paper-default run and an unknown key are refused."""
    import importlib.util
    import json
    import subprocess
    import sys

    from cerpe.pipeline.devreport import checks, report
    from cerpe.pipeline.graphdev import GraphDevError, dev_sets

    root, _, _, out = runs
    (tmp_path / "runs").mkdir()
    (tmp_path / "runs" / "toy").symlink_to(root, target_is_directory=True)
    spec = importlib.util.spec_from_file_location("dev_graph_replay", Path(__file__).parents[1] / "scripts" /
                                                  "dev_graph_replay.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    sets = dev_sets(tmp_path / "runs")
    assert [d.name for d in sets] == ["toy"]
    summary, per_set = script.judge(sets, AlgorithmConfig().graph)
    table, _ = report([("toy", out["cerpe"]), ("toy", out["cerpe-graph"])])
    want = checks(table)
    for c in want.itertuples(index=False):
        if c.check.startswith("20 "):
            assert summary[c.check] == [int(c.result == "pass"), int(c.result != "n/a")], c.check
    rows = table.set_index("method")
    assert summary["geo_ratio"] == pytest.approx(rows.loc["cerpe-graph", "e_pos_m"] / rows.loc["cerpe", "e_pos_m"])
    assert per_set == [f"toy {summary['geo_ratio']:.3f}"]
    loose, _ = script.judge(sets, dataclasses.replace(AlgorithmConfig().graph, direct_rot_rad=0.2, direct_trans_rel=0.5))
    assert loose["geo_ratio"] != pytest.approx(summary["geo_ratio"])
    assert script.grid(["kernel_k=1,2", "kernel=huber"]) == [{"kernel_k": 1, "kernel": "huber"},
                                                             {"kernel_k": 2, "kernel": "huber"}]
    bad = tmp_path / "paper" / "synthetic-cad" / "cerpe-graph"
    bad.mkdir(parents=True)
    (bad / "run.json").write_text(json.dumps({"manifest": "build/paper-default/synthetic-cad.yaml"}))
    with pytest.raises(GraphDevError, match="paper-default"):
        dev_sets(tmp_path / "paper")
    res = subprocess.run([sys.executable, str(Path(__file__).parents[1] / "scripts" / "dev_graph_replay.py"),
                          "--runs", str(tmp_path / "runs"), "--set", "kernel_kk=1"], capture_output=True, text=True)
    assert res.returncode != 0 and "unknown option(s) 'kernel_kk'; known:" in res.stderr and "kernel_k," in res.stderr
