"""mocap adapter: real TUM frames (when ../shared is present), known-answer fixtures, sync helpers."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from cerpe.datasets import LoadReport, load_manifest, load_setting
from cerpe.datasets.sync import nearest, poses_at, synchronise, window_mask
from cerpe.geometry import random_se3, se3_from_tq_xyzw, se3_inverse
from test_datasets_fixtures import CAMERA, SHARED, T_BODY_CAM, W, H, body_pose, write_mocap

TUM = SHARED / "tum-fr3-office"


def tum_split_manifest(tmp: Path) -> Path:
    """Two robots from the real TUM frames: the first 8 s and the last 8 s, synchronised by index."""
    p = tmp / "tum.yaml"
    p.write_text(yaml.safe_dump({
        "name": "tum-fr3-office-split", "adapter": "mocap", "enabled": True, "data_root": str(TUM),
        "metric_depth": "none", "sync_tolerance_s": 0.02,
        "encounters": [{"name": "office", "sync": "index", "robots": [
            {"id": "first", "images": "rgb", "trajectory": "groundtruth.txt", "intrinsics": "camera.yaml",
             "window_s": [0.0, 8.0]},
            {"id": "last", "images": "rgb", "trajectory": "groundtruth.txt", "intrinsics": "camera.yaml",
             "window_s": [-8.0, None]},
        ]}]}))
    return p


@pytest.mark.shared_data
@pytest.mark.skipif(not TUM.is_dir(), reason="../shared/data/tum-fr3-office not present")
def test_real_tum_frames_split_into_two_robots(tmp_path: Path) -> None:
    report = LoadReport()
    setting = load_setting(tum_split_manifest(tmp_path), report)
    (enc,) = setting.encounters
    first, last = enc.robots
    assert enc.n_steps == 8
    all_stamps = sorted(float(p.stem) for p in (TUM / "rgb").glob("*.png"))
    np.testing.assert_array_equal(first.stamps_s, all_stamps[:8])
    np.testing.assert_array_equal(last.stamps_s, all_stamps[-8:])
    # poses: straight from groundtruth.txt (exact stamps, camera-to-world, quaternion scalar-last)
    gt = {round(r[0], 6): r[1:] for r in np.loadtxt(TUM / "groundtruth.txt", comments="#")}
    assert not first.has_gt(0)  # the first frame has no ground-truth row: NaN, counted
    assert report.counts[("office", "first: frames without ground-truth pose")] == 1
    for rob in (first, last):
        for t in range(len(rob)):
            row = gt.get(round(rob.stamps_s[t], 6))
            if row is None:
                continue
            np.testing.assert_allclose(rob.T_world_cam[t], se3_from_tq_xyzw(row[:3], row[3:]), atol=1e-12)
    assert sum(first.has_gt(t) for t in range(8)) == 7 and all(last.has_gt(t) for t in range(8))
    cam = yaml.safe_load((TUM / "camera.yaml").read_text())
    K = first.intrinsics
    assert (K.fx, K.fy, K.cx, K.cy, K.width, K.height) == (cam["fx"], cam["fy"], cam["cx"], cam["cy"], 640, 480)
    assert first.image(1).shape == (480, 640, 3)
    # ground-truth relative pose at step 1 equals the composition of the two file rows
    T = enc.gt_T_cj_ci(1, 0, 1)
    np.testing.assert_allclose(T, se3_inverse(last.T_world_cam[1]) @ first.T_world_cam[1], atol=1e-12)


@pytest.mark.parametrize("fmt", ["tum", "euroc", "csv"])
def test_formats_interpolation_extrinsic_and_sync(tmp_path: Path, fmt: str) -> None:
    setting = load_setting(write_mocap(tmp_path, fmt=fmt))
    (enc,) = setting.encounters
    assert enc.n_steps == 6 and enc.robot_ids == ["r0", "r1"]
    for r, rob in enumerate(enc.robots):
        for t in range(6):
            expected = body_pose(r, rob.stamps_s[t] - 1000.0) @ T_BODY_CAM
            # SLERP over 20 ms of a 0.4 rad/s yaw is exact up to the file's 9 decimals; translation is linear
            np.testing.assert_allclose(rob.T_world_cam[t], expected, atol=2e-6)
        assert rob.depth_m(0).max() == pytest.approx(2.0) and rob.depth_m(0).shape == (H, W)
    sync = setting.meta["load_report"]["sync"]["enc0"]
    assert sync["r1"]["max_abs_s"] == pytest.approx(0.005, abs=1e-6)
    np.testing.assert_allclose(enc.overlap[:, 0, 1], np.arange(6) / 6)
    assert setting.metric_depth == "sensor" and setting.meta["evaluation_every"] == 1


def test_nearest_pose_without_interpolation_and_tolerance(tmp_path: Path) -> None:
    m = write_mocap(tmp_path, interpolate=False, depth=False, overlap=False)
    doc = yaml.safe_load(m.read_text())
    for rob in doc["encounters"][0]["robots"]:
        rob["gt_tolerance_s"] = 0.001  # images at x.x05 s are 5 ms from the 50 Hz samples of robot 1
    m.write_text(yaml.safe_dump(doc))
    report = LoadReport()
    setting = load_setting(m, report)
    r0, r1 = setting.encounters[0].robots
    assert all(r0.has_gt(t) for t in range(6))  # robot 0 images sit exactly on samples
    assert not any(r1.has_gt(t) for t in range(6))  # nothing within 1 ms: NaN, never a wrong pose
    assert report.counts[("enc0", "r1: frames without ground-truth pose")] == 6


def test_stamp_sync_drops_and_reports_unmatched_frames(tmp_path: Path) -> None:
    m = write_mocap(tmp_path, depth=False, overlap=False)
    next(iter(sorted((tmp_path / "enc0" / "r1" / "rgb").iterdir()))).unlink()  # r1 loses its first frame
    report = LoadReport()
    setting = load_setting(m, report)
    enc = setting.encounters[0]
    assert enc.n_steps == 5 and enc.robots[0].stamps_s[0] == pytest.approx(1000.1)
    assert report.counts[("enc0", "reference frames without partner frames within sync_tolerance_s (dropped)")] == 1


def test_list_file_window_and_overlap_rows(tmp_path: Path) -> None:
    m = write_mocap(tmp_path)
    rgb = tmp_path / "enc0" / "r0" / "rgb"
    (tmp_path / "enc0" / "r0" / "rgb.txt").write_text(
        "# stamp path\n" + "".join(f"{p.stem} rgb/{p.name}\n" for p in sorted(rgb.iterdir())))
    doc = yaml.safe_load(m.read_text())
    doc["encounters"][0]["robots"][0]["images"] = "enc0/r0/rgb.txt"
    doc["encounters"][0]["window_s"] = [0.15, None]
    m.write_text(yaml.safe_dump(doc))
    enc = load_setting(m).encounters[0]
    assert enc.n_steps == 4
    np.testing.assert_allclose(enc.overlap[:, 1, 0], np.arange(2, 6) / 6)  # rows follow robot 0's kept frames


def test_camera_yaml_roundtrip_matches(tmp_path: Path) -> None:
    K = load_setting(write_mocap(tmp_path)).encounters[0].robots[0].intrinsics
    assert (K.fx, K.fy, K.cx, K.cy, K.width, K.height) == (CAMERA["fx"], CAMERA["fy"], CAMERA["cx"], CAMERA["cy"], W, H)


def test_disabled_manifest_validates_without_data(tmp_path: Path) -> None:
    p = tmp_path / "m.yaml"
    p.write_text("name: later\nadapter: mocap\nenabled: false\ndata_root: ${SURELY_UNSET_CERPE_VAR}/x\n"
                 "encounters:\n  - name: e\n    robots:\n      - {id: a, images: a, intrinsics: c.yaml}\n"
                 "      - {id: b, images: b, intrinsics: c.yaml}\n")
    m = load_manifest(p)
    assert not m.enabled and m.data_root is None


def test_data_root_env_expansion(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    write_mocap(tmp_path / "data")
    doc = yaml.safe_load((tmp_path / "data" / "manifest.yaml").read_text())
    doc["data_root"] = "${CERPE_TEST_ROOT}/data"
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(doc))
    monkeypatch.setenv("CERPE_TEST_ROOT", str(tmp_path))
    assert load_manifest(tmp_path / "m.yaml").data_root == (tmp_path / "data").resolve()


# --------------------------------------------------------------------------- sync helpers
def test_nearest_known_answer() -> None:
    idx, dt = nearest(np.array([0.0, 0.49, 0.51, 2.0, 10.0]), np.array([0.0, 0.5, 1.0, 2.1]), 0.05)
    np.testing.assert_array_equal(idx, [0, 1, 1, -1, -1])
    np.testing.assert_allclose(dt[:3], [0.0, 0.01, -0.01], atol=1e-12)
    assert np.isnan(dt[3])


def test_poses_at_interpolates_only_small_gaps() -> None:
    rng = np.random.default_rng(3)
    T0, T1 = random_se3(rng), random_se3(rng)
    T = np.stack([T0, T1, T1])
    stamps = np.array([0.0, 0.1, 5.0])
    out = poses_at(np.array([0.0, 0.05, 2.5]), stamps, T, tol_s=0.01, interpolate=True, max_gap_s=0.2)
    np.testing.assert_allclose(out[0], T0, atol=1e-12)
    np.testing.assert_allclose(out[1][:3, 3], (T0[:3, 3] + T1[:3, 3]) / 2, atol=1e-12)
    assert np.all(np.isnan(out[2]))  # the 4.9 s gap is not bridged


def test_synchronise_one_partner_frame_per_step() -> None:
    a = np.array([0.0, 0.1, 0.2, 0.3])
    b = np.array([0.005, 0.21])  # 0.1 is 0.095 from 0.005: too far; 0.2 <-> 0.21 ok
    idx, res, dropped = synchronise([a, b], 0.02)
    np.testing.assert_array_equal(idx[0], [0, 2])
    np.testing.assert_array_equal(idx[1], [0, 1])
    np.testing.assert_allclose(res[1], [0.005, 0.01], atol=1e-12)
    assert dropped == 2
    # two reference frames compete for one partner frame: the closer one keeps it
    idx, _, _ = synchronise([np.array([0.0, 0.0005]), np.array([0.0004])], 0.01)
    np.testing.assert_array_equal(idx[0], [1])


def test_window_mask_relative_and_from_end() -> None:
    s = np.arange(0.0, 10.0, 1.0) + 100
    assert window_mask(s, [0, 3]).sum() == 4
    assert window_mask(s, [-2, None]).nonzero()[0].tolist() == [7, 8, 9]
    assert window_mask(s, None).all()


def test_metric_depth_options_reach_the_setting_and_the_depth_source(tmp_path: Path) -> None:
    from cerpe.backbones.depth import DepthSourceError, build_depth_source
    from cerpe.datasets import ManifestError

    m = write_mocap(tmp_path)
    raw = yaml.safe_load(m.read_text())
    raw["metric_depth_options"] = {"min_m": 0.5, "max_m": 40}
    m.write_text(yaml.safe_dump(raw))
    setting = load_setting(m)
    assert setting.metric_depth_options == {"min_m": 0.5, "max_m": 40}
    src = build_depth_source(setting.metric_depth, setting.metric_depth_options)
    assert (src.min_m, src.max_m) == (0.5, 40)
    with pytest.raises(DepthSourceError, match="bad options.*max_range"):
        build_depth_source("sensor", {"max_range": 40})
    for bad, field in (([40], "metric_depth_options"), ({"max_m": [1, 2]}, "metric_depth_options.max_m")):
        raw["metric_depth_options"] = bad
        m.write_text(yaml.safe_dump(raw))
        with pytest.raises(ManifestError, match=field.replace(".", r"\.")):
            load_manifest(m)


def test_a_misspelt_depth_option_is_an_error_naming_the_file_in_check_and_run(tmp_path: Path) -> None:
    """``dataset`` and ``none`` took any option and ignored it; now every source names an unknown one."""
    from cerpe.backbones.depth import DepthSourceError, build_depth_source
    from cerpe.datasets.cli import check_one
    from cerpe.pipeline.run import RunError, run_method

    assert build_depth_source("dataset", {"rel_sigma": 0.02}).rel_sigma == 0.02
    for name, opts in (("dataset", {"rel_sigmaa": 0.02}), ("none", {"rel_sigma": 0.0}), ("dataset", {"rel_sigma": -1})):
        with pytest.raises(DepthSourceError, match="rel_sigma"):
            build_depth_source(name, opts)
    m = write_mocap(tmp_path)
    raw = yaml.safe_load(m.read_text())
    raw["metric_depth"], raw["metric_depth_options"] = "dataset", {"rel_sigmaa": 0.02}
    m.write_text(yaml.safe_dump(raw))
    problems = check_one(str(m), None, False, False)
    assert len(problems) == 1 and str(m) in problems[0] and "metric_depth_options" in problems[0] \
        and "rel_sigmaa" in problems[0]
    with pytest.raises(RunError, match="metric_depth_options.*rel_sigmaa") as exc:
        run_method(m, "cerpe", tmp_path / "run", progress=False)
    assert str(m.resolve()) in str(exc.value)
    assert not (tmp_path / "run").exists()  # nothing written


def test_synth_manifest_gives_the_cad_world_an_outdoor_sensor() -> None:
    from cerpe.synth import sensor_options

    assert sensor_options("cad-intersection")["max_m"] >= 40
    assert sensor_options("indoor-team") == {}


def test_distorted_camera_is_undistorted_once_on_load(tmp_path: Path) -> None:
    """A camera.yaml with distortion: colour (bilinear) and 16-bit depth (nearest) are undistorted with
    the same maps and the loaded intrinsics describe the undistorted images."""
    import cv2

    m = write_mocap(tmp_path, n_frames=2)
    dist = [-0.25, 0.08, 0.001, -0.002, 0.0]
    cam = dict(CAMERA, distortion=dist)
    rng = np.random.default_rng(3)
    for r in range(2):
        (tmp_path / "enc0" / f"r{r}" / "camera.yaml").write_text(yaml.safe_dump(cam))
        for f in (tmp_path / "enc0" / f"r{r}" / "depth").glob("*.png"):  # a depth ramp, so nearest vs blend shows
            cv2.imwrite(str(f), (1000 + 50 * np.arange(W)[None, :] + 0 * np.arange(H)[:, None]).astype(np.uint16))
        for f in (tmp_path / "enc0" / f"r{r}" / "rgb").glob("*.png"):
            cv2.imwrite(str(f), rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
    rob = load_setting(m).encounters[0].robots[0]
    K0 = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1.0]])
    assert not np.allclose(rob.intrinsics.K, K0)  # the undistorted camera
    raw = cv2.imread(str(sorted((tmp_path / "enc0" / "r0" / "rgb").glob("*.png"))[0]))
    mapx, mapy = cv2.initUndistortRectifyMap(K0, np.array(dist), None, rob.intrinsics.K, (W, H), cv2.CV_32FC1)
    want = cv2.remap(raw, mapx, mapy, cv2.INTER_LINEAR)[:, :, ::-1]
    np.testing.assert_array_equal(rob.image(0), want)
    d = rob.depth_m(0)
    assert d.shape == (H, W) and d.max() <= (1000 + 50 * (W - 1)) / 1000 + 1e-6
    stored = {(1000 + 50 * u) / 1000 for u in range(W)} | {0.0}
    assert {float(np.float32(v)) for v in np.unique(d)} <= {float(np.float32(v)) for v in stored}  # nearest: no blends


def test_distorted_camera_with_npy_depth_is_refused(tmp_path: Path) -> None:
    from cerpe.datasets import ManifestError

    m = write_mocap(tmp_path, n_frames=2)
    for r in range(2):
        (tmp_path / "enc0" / f"r{r}" / "camera.yaml").write_text(yaml.safe_dump(dict(CAMERA, distortion=[0.1, 0, 0, 0, 0])))
        for f in (tmp_path / "enc0" / f"r{r}" / "depth").glob("*.png"):
            np.save(f.with_suffix(".npy"), np.full((H, W), 2.0, np.float32))
            f.unlink()
    with pytest.raises(ManifestError, match=r"robots\[0\]\.depth.*16-bit PNG"):
        load_setting(m)
