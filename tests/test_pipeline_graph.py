"""cerpe-graph through the pipeline: run folder (steps.csv sigmas, the .cov companion of the TUM
file), Table I's extension row, the calibration figure and data. (The replay of recorded passes and
the noise models' fit, development tools: tests/test_lab_graph.py.)"""
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
from cerpe import methods
from cerpe.pipeline import paper, table1
from cerpe.pipeline import run as rp
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
