"""`cerpe bench` accuracy checks (issue 4) on known trajectories, and the command itself on a tiny suite."""
from __future__ import annotations

import numpy as np
import pytest

from cerpe import geometry as G
from cerpe.pipeline.bench_walk import _ego_steps, ego_summary


def _traj(n: int = 11, step_m: float = 0.1, yaw_deg: float = 1.0) -> np.ndarray:
    """``[n,4,4]`` camera-to-world poses moving ``step_m`` along z and turning ``yaw_deg`` per step."""
    out, T = [], np.eye(4)
    for _ in range(n):
        out.append(T.copy())
        T = T @ G.make_se3(G.so3_exp(np.radians([0, yaw_deg, 0])), np.array([0, 0, step_m]))
    return np.stack(out)


def test_perfect_odometry_has_zero_error_in_any_odometry_frame():
    gt = _traj()
    offset = G.make_se3(G.so3_exp(np.array([0.1, -0.3, 0.2])), np.array([1.0, 2.0, 3.0]))
    X = [offset @ T for T in gt]  # odometry frame differs from the world frame
    s = ego_summary([_ego_steps(X, gt)])
    assert s["rpe_trans_pct"] == pytest.approx(0, abs=1e-9)
    assert s["rpe_rot_deg_median"] == pytest.approx(0, abs=1e-6)
    assert s["end_drift_pct"] == pytest.approx(0, abs=1e-9)
    assert s["path_m"] == pytest.approx(1.0) and s["n_steps"] == 10


def test_scale_error_gives_that_percentage_per_step():
    gt = _traj(yaw_deg=0.0)
    X = [G.make_se3(T[:3, :3], 1.05 * T[:3, 3]) for T in gt]  # 5 % too long
    s = ego_summary([_ego_steps(X, gt)])
    assert s["rpe_trans_pct"] == pytest.approx(5.0)
    assert s["end_drift_pct"] == pytest.approx(5.0)


def test_frozen_odometry_is_100_percent_and_suite_pools_paths():
    gt = _traj()
    frozen = [np.eye(4)] * len(gt)
    a = _ego_steps(frozen, gt)
    b = _ego_steps(list(gt), gt)
    assert ego_summary([a])["rpe_trans_pct"] == pytest.approx(100.0)
    assert ego_summary([a, b])["rpe_trans_pct"] == pytest.approx(50.0)  # pooled over both paths
    assert ego_summary([a])["rpe_rot_deg_median"] == pytest.approx(1.0, rel=1e-6)


def test_no_motion_or_missing_ground_truth_gives_nan_not_an_error():
    still = np.stack([np.eye(4)] * 4)
    assert np.isnan(ego_summary([_ego_steps(list(still), still)])["rpe_trans_pct"])
    gt = _traj(4)
    gt[2] = np.nan
    assert np.isnan(ego_summary([_ego_steps(list(_traj(4)), gt)])["rpe_trans_pct"])


def test_suite_printout_carries_the_gate_figures():
    import pandas as pd

    from cerpe.pipeline.bench_report import format_accuracy
    from cerpe.pipeline.bench_walk import median_p90
    from cerpe.pipeline.evaluate import gate_quality

    rows = []
    for step, score, o01, o10 in [(0, 0.9, 0.5, 0.5), (1, 0.6, 0.5, 0.1), (2, 0.3, 0.0, 0.0), (3, 0.7, 0.0, 0.0)]:
        rows += [{"encounter": "e", "step": step, "ego": "r0", "other": "r1", "gate_score": score, "overlap_gt": o01},
                 {"encounter": "e", "step": step, "ego": "r1", "other": "r0", "gate_score": score, "overlap_gt": o10}]
    gate = gate_quality(pd.DataFrame(rows), tau=0.65)
    text = "\n".join(format_accuracy({"direct_rot_err_rad": median_p90([0.01]), "ego_per_robot": {}, "gate": gate}))
    assert f"ROC AUC {gate['roc_auc']:.3f}" in text and "at tau 0.6500" in text
    assert f"precision {gate['precision']:.3f}, recall {gate['recall']:.3f}" in text
    assert "symmetric score can reach 0.967" in text and "25 % of ordered pairs" in text
    # the co-visibility label: step 0 positive (0.9), steps 2-3 negative (0.3, 0.7), step 1 left out
    assert "over 3 pairs (1 positive, 1 left out): ROC AUC 1.000" in text
    assert "precision 0.500, recall 1.000 (targets >= 0.8)" in text  # open at 0.65: 0.9 and 0.7
    assert "gate" not in "\n".join(format_accuracy({"direct_rot_err_rad": median_p90([]), "ego_per_robot": {}}))


def test_ego_table_says_which_robot_misses_its_targets():
    from cerpe.pipeline.bench_report import format_accuracy
    from cerpe.pipeline.bench_walk import median_p90

    def ego(trans: float, rot: float) -> dict:
        return {"rpe_trans_pct": trans, "rpe_rot_deg_median": rot, "end_drift_pct": 0.1, "path_m": 1.0, "n_steps": 9}

    text = "\n".join(format_accuracy({"direct_rot_err_rad": median_p90([0.01]), "ego_per_robot": {
        "r0": ego(10.9, 0.004), "r1": ego(0.3, 0.004), "r2": ego(1.0, 0.7), "r3": ego(float("nan"), float("nan"))}}))
    rows = {line.split()[0]: line for line in text.splitlines() if line.strip().startswith("r")}
    assert rows["r0"].endswith("NOT met (trans)") and rows["r1"].endswith("   met")
    assert rows["r2"].endswith("NOT met (rot)") and rows["r3"].endswith("n/a")
    assert "(targets: < 2 %, < 0.5 deg median)" in text


def test_bench_renders_the_default_suite_once_then_reuses_it(tmp_path, monkeypatch, capsys):
    """A fresh clone: `cerpe bench` renders its default suite into the cache `make paper` uses
    ($CERPE_CACHE here), runs 2 and 3 robots against the paper's 438 / 780 ms; the next run renders nothing."""
    from cerpe.cli import main
    from cerpe.synth import writer

    tiny = {"seed": 0, "n_encounters": 1, "n_frames": 3, "fps": 2.0, "size": (160, 120), "n_robots": 3}
    monkeypatch.setitem(writer.SUITES, "paper-default", {"synthetic-indoor": ("indoor-team", tiny)})
    monkeypatch.setenv("CERPE_CACHE", str(tmp_path / "cache"))
    monkeypatch.chdir(tmp_path)  # the default manifest is the checkout's, wherever bench runs from
    argv = ["bench", "--steps", "2", "--warmup", "0", "--encounters", "1", "--width", "160", "--height", "120"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "== 2 robots" in out and "(target 438 ms:" in out
    assert "== 3 robots" in out and "(target 780 ms:" in out
    suite = tmp_path / "cache" / "synth" / "paper-default" / "indoor-team-seed0"
    png = next(suite.rglob("*.png"))
    before = png.stat().st_mtime_ns
    assert main(argv) == 0  # as after `make paper`: the suite is there
    assert png.stat().st_mtime_ns == before


def test_printout_carries_the_cross_robot_registration_counters():
    from cerpe.pipeline.bench_report import format_table
    from cerpe.pipeline.bench_walk import median_p90

    r = {"n_robots": 2, "team_step_ms": median_p90([300.0]), "target_ms": 438.0, "xfeat_passes_per_robot_step": 1.0,
         "peak_rss_mib": 1.0, "gate_open_ratio": 0.5, "stage_ms": {}, "robot_step_ms": median_p90([150.0]),
         "bytes_per_robot_step": {}, "accuracy": {"direct_rot_err_rad": median_p90([]), "ego_per_robot": {}},
         "cross": {"gated_pairs": 10, "cross-registered": 6, "cross-none": 4, "cross-learned": 3,
                   "cross-learned-pairs": 7}}
    text = format_table([r], {"dim": 8, "wire_bytes": {}})
    assert ("cross-robot registration (all steps): 10 gated pairs, 6 collaborator views registered, 4 not; "
            "learned matcher for 3 views (7 image pairs)") in text
    r["cross"] = {"gated_pairs": 10}  # a backbone without the counters (VGGT): no line
    assert "cross-robot" not in format_table([r], {"dim": 8, "wire_bytes": {}})


def test_printout_leaves_a_sensors_depth_out_of_the_robots_work():
    """With depth from a sensor, the robot's step is all stages less the sensor's part, and the line
    below it gives the step with it; a depth network (no sensor part) keeps the "all stages" row."""
    from cerpe.pipeline.bench_report import format_table
    from cerpe.pipeline.bench_walk import median_p90

    r = {"n_robots": 2, "team_step_ms": median_p90([300.0]), "target_ms": 438.0, "xfeat_passes_per_robot_step": 1.0,
         "peak_rss_mib": 1.0, "gate_open_ratio": 0.5, "stage_ms": {"scale": median_p90([9.0])},
         "robot_step_ms": median_p90([92.0]), "sensor_ms": median_p90([8.0]),
         "robot_step_with_sensor_ms": median_p90([100.0]), "robot_target_ms": 100.0,
         "bytes_per_robot_step": {}, "accuracy": {"direct_rot_err_rad": median_p90([]), "ego_per_robot": {}}}
    lines = format_table([r], {"dim": 8, "wire_bytes": {}}).splitlines()
    row = next(line.split() for line in lines if line.strip().startswith("robot's work"))
    assert row[2:5] == ["92.0", "92.0", "92.0"]
    assert next(line.split() for line in lines if line.strip().startswith("sensor"))[1:4] == ["8.0"] * 3
    assert next(line.split() for line in lines if "with the sensor" in line)[3:6] == ["100.0"] * 3
    r["sensor_ms"] = median_p90([0.0])
    text = format_table([r], {"dim": 8, "wire_bytes": {}})
    assert "all stages" in text and "robot's work" not in text and "with the sensor" not in text


def _sweep_row(n: int, wall_ms: float, late: list[int] | None) -> dict:
    from cerpe.pipeline.bench_walk import median_p90

    reg = None if late is None else {"late_steps": median_p90(late)}
    return {"n_robots": n, "robot_step_ms": median_p90([wall_ms]), "robot_step_cpu_ms": median_p90([wall_ms / 2]),
            "bytes_per_robot_step": {"total": median_p90([1000.0 * n])}, "gate_score_cpu_ms": median_p90([0.25]),
            "registration": reg}


def test_sweep_growth_is_against_the_smallest_team():
    from cerpe.pipeline.bench_report import format_sweep

    text = format_sweep([_sweep_row(2, 100.0, [0, 1]), _sweep_row(8, 140.0, [2])])
    assert "8 robots against 2: 1.40x (target <= 1.5x: met)" in text
    row8 = next(line.split() for line in text.splitlines() if line.split()[:1] == ["8"])
    assert row8[:6] == ["8", "140.0", "140.0", "70.0", "70.0", "1.40"] and row8[6:8] == ["8000", "250"]
    text = format_sweep([_sweep_row(2, 100.0, None), _sweep_row(5, 151.0, None)])  # inline: no lateness
    assert "5 robots against 2: 1.51x (target <= 1.5x: NOT met)" in text and "nan" in text


@pytest.mark.parametrize("registration", ["worker", "inline"])
def test_team_sweep_beyond_the_suite_renders_one_team_encounter(tmp_path, monkeypatch, capsys, registration):
    """--robots beyond the suite's teams: every size runs on one rendered indoor-team encounter of the
    largest team; the sweep table, the registration counters (worker) and the report's fields."""
    import json

    from cerpe.cli import main
    from cerpe.synth import writer

    tiny = {"seed": 0, "n_encounters": 1, "n_frames": 3, "fps": 2.0, "size": (160, 120), "n_robots": 2}
    monkeypatch.setitem(writer.SUITES, "paper-default", {"synthetic-indoor": ("indoor-team", tiny)})
    monkeypatch.setenv("CERPE_CACHE", str(tmp_path / "cache"))
    monkeypatch.chdir(tmp_path)
    out_json = tmp_path / "bench.json"
    argv = ["bench", "--robots", "2", "4", "--steps", "3", "--warmup", "1", "--width", "160", "--height", "120",
            "--registration", registration, "--graph-seconds", "1", "--out", str(out_json)]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "indoor-team seed 7, 4 robots, 3 steps" in out
    assert "== 2 robots" in out and "== 4 robots" in out and "4 robots against 2:" in out
    assert ("registration apart from the step:" in out) == (registration == "worker")
    report = json.loads(out_json.read_text())
    assert report["registration"] == registration and [r["n_robots"] for r in report["results"]] == [2, 4]
    assert report["xfeat_precision"] == "fp32" and "models offline, XFeat fp32;" in out  # preset paper
    for r in report["results"]:
        assert set(r["stage_cpu_ms"]) == set(r["stage_ms"]) and r["gate_score_cpu_ms"]["n"] == 2 * r["n_robots"]
        assert (r["registration"] is None) == (registration == "inline")
        assert {"match", "vote", "dense", "pose", "total"} <= set(r["backbone_pass_ms"])
        # the simulated depth sensor's part of "scale", left out of the robot's work (sensor: true)
        assert r["sensor_ms"]["median"] > 0
        assert r["robot_step_with_sensor_ms"]["median"] > r["robot_step_ms"]["median"]
    assert "\n     dense " in out and "\n     pose " in out  # the backbone's profile, under its stage
