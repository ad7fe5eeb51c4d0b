"""OpenMARS adapter on a tiny nuScenes-format fixture built here (json tables, images, LiDAR bins).

Scene ``s3`` has three vehicles on a flat world (z up):
  * A at the origin facing +x, B at (10, 0, 0) facing -x, C at (0, 10, 0) facing -y;
  * every camera sits 1.5 m ahead of and 1.6 m above its ego origin, looking forward
    (ego x forward, y left, z up  ->  camera z forward, x right, y down).
The expected relative poses below are worked out by hand from that picture,
independently of the adapter's matrix products.
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from cerpe.datasets import ManifestError, load_setting
from cerpe.datasets.openmars import LidarDepth, project_points
from cerpe.scene import SceneError

W, H, FX, FY, CX, CY = 64, 48, 50.0, 52.0, 32.0, 24.0
# camera-to-ego rotation: camera (x right, y down, z forward) in ego (x fwd, y left, z up)
R_EGO_CAM = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float)
Q_EGO_CAM_WXYZ = [0.5, -0.5, 0.5, -0.5]


def _yaw_wxyz(yaw: float) -> list[float]:
    return [float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2))]


def build_fixture(root: Path, lidar_points: dict | None = None, camera_dt_us: int = 10_000) -> Path:
    """Write a 2-scene OpenMARS-style dataset under ``root``; returns ``root``.

    Scene ``s3`` (3 vehicles A, B, C, 3 time steps, LiDAR on A) and scene ``s2``
    (2 vehicles A, B, 2 steps). Vehicles stand still; B's images are
    ``camera_dt_us`` later than A's, C's 5 ms earlier.
    """
    tv = root / "v1.0"
    tv.mkdir(parents=True)
    rng = np.random.default_rng(0)
    poses = {"A": ([0.0, 0.0, 0.0], 0.0), "B": ([10.0, 0.0, 0.0], np.pi), "C": ([0.0, 10.0, 0.0], -np.pi / 2)}
    offsets = {"A": 0, "B": camera_dt_us, "C": -5_000}
    tabs: dict[str, list] = {k: [] for k in ("scene", "sample", "sample_data", "calibrated_sensor", "ego_pose", "sensor", "log")}
    for v in poses:
        for ch, mod in (("CAM_FRONT_CENTER", "camera"), ("LIDAR_FRONT_CENTER", "lidar")):
            tabs["sensor"].append({"token": f"sen-{ch}-{v}", "channel": f"{ch}_{v}", "modality": mod})
        tabs["calibrated_sensor"].append({
            "token": f"cs-cam-{v}", "sensor_token": f"sen-CAM_FRONT_CENTER-{v}", "translation": [1.5, 0.0, 1.6],
            "rotation": Q_EGO_CAM_WXYZ, "camera_intrinsic": [[FX, 0, CX], [0, FY, CY], [0, 0, 1]],
            "distortion_coefficient": [0.1, -0.2, 0.0, 0.0]})
        tabs["calibrated_sensor"].append({
            "token": f"cs-lidar-{v}", "sensor_token": f"sen-LIDAR_FRONT_CENTER-{v}", "translation": [1.0, 0.0, 1.8],
            "rotation": [1.0, 0.0, 0.0, 0.0]})
    t0 = 1_696_454_482_000_000
    for scene, vehicles, n_steps in (("s3", "ABC", 3), ("s2", "AB", 2)):
        sample_tokens = []
        for k in range(n_steps):
            st = f"{scene}-sample-{k}"
            sample_tokens.append(st)
            ts = t0 + k * 100_000
            tabs["sample"].append({"token": st, "timestamp": ts, "scene_token": scene,
                                   "prev": "", "next": "", "data": {}, "anns": []})
            for v in vehicles:
                tcam = ts + offsets[v]
                t, yaw = poses[v]
                ep = f"{scene}-ep-{v}-{k}"
                tabs["ego_pose"].append({"token": ep, "timestamp": tcam, "translation": t, "rotation": _yaw_wxyz(yaw)})
                fn = f"sweeps/CAM_FRONT_CENTER_{v}/{tcam}.jpg"
                (root / fn).parent.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(root / fn), rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
                tabs["sample_data"].append({
                    "token": f"{scene}-sd-cam-{v}-{k}", "sample_token": st, "ego_pose_token": ep,
                    "calibrated_sensor_token": f"cs-cam-{v}", "timestamp": tcam, "fileformat": "jpg",
                    "is_key_frame": True, "height": H, "width": W, "filename": fn, "prev": "", "next": ""})
                if v == "A" and scene == "s3":
                    # the LiDAR sweep is 20 ms after the image; the vehicle has moved 1 m forward by then
                    tl = tcam + 20_000
                    epl = f"{scene}-ep-lidar-{v}-{k}"
                    tabs["ego_pose"].append({"token": epl, "timestamp": tl, "translation": [1.0, 0.0, 0.0],
                                             "rotation": _yaw_wxyz(0.0)})
                    fl = f"sweeps/LIDAR_FRONT_CENTER_{v}/{tl}.pcd.bin"
                    (root / fl).parent.mkdir(parents=True, exist_ok=True)
                    pts = (lidar_points or {}).get(k, np.zeros((0, 5), np.float32))
                    np.asarray(pts, dtype=np.float32).tofile(root / fl)
                    tabs["sample_data"].append({
                        "token": f"{scene}-sd-lidar-{v}-{k}", "sample_token": st, "ego_pose_token": epl,
                        "calibrated_sensor_token": f"cs-lidar-{v}", "timestamp": tl, "fileformat": "pcd",
                        "is_key_frame": True, "height": 0, "width": 0, "filename": fl, "prev": "", "next": ""})
        tabs["scene"].append({"token": scene, "name": f"scene_{scene}", "log_token": "log0", "nbr_samples": n_steps,
                              "first_sample_token": sample_tokens[0], "last_sample_token": sample_tokens[-1],
                              "vehicle_list": [f"{v}" for v in vehicles], "description": ""})
    tabs["log"].append({"token": "log0", "logfile": "", "vehicle": "fleet", "date_captured": "2023-10-04", "location": "x"})
    for name, rows in tabs.items():
        (tv / f"{name}.json").write_text(json.dumps(rows))
    return root


def _manifest(tmp: Path, body: str) -> Path:
    p = tmp / "openmars.yaml"
    p.write_text("name: openmars-fixture\nadapter: openmars\ndata_root: data\nmetric_depth: dataset\n"
                 "sync_tolerance_s: 0.05\n" + body)
    return p


# one LiDAR point 11 m ahead / 0.5 m left of the LiDAR, one behind it on the same ray, one behind the camera
LIDAR_PTS = np.array([[11.0, 0.5, -0.2, 7, 1], [22.0, 1.0, -0.4, 9, 1], [-5.0, 0.0, -0.2, 3, 2]], np.float32)


@pytest.fixture()
def dataset(tmp_path: Path) -> Path:
    build_fixture(tmp_path / "data", lidar_points={0: LIDAR_PTS})
    return tmp_path


def test_three_vehicle_ground_truth_matches_hand_computed(dataset: Path) -> None:
    m = _manifest(dataset, "encounters:\n  - scene: scene_s3\n")
    setting = load_setting(m)
    (enc,) = setting.encounters
    assert enc.robot_ids == ["A", "B", "C"] and enc.n_steps == 3
    # A's camera seen from B's: 7 m straight ahead of B, turned by 180 deg about the camera y axis
    expected_BA = np.array([[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 7.0], [0, 0, 0, 1]])
    np.testing.assert_allclose(enc.gt_T_cj_ci(1, 0, 1), expected_BA, atol=1e-9)
    # A's camera seen from C's: x = -1.5, z = 8.5; A's x axis = C's z, A's y = C's y, A's z = -C's x
    expected_CA = np.array([[0, 0, -1, -1.5], [0, 1, 0, 0], [1, 0, 0, 8.5], [0, 0, 0, 1]])
    np.testing.assert_allclose(enc.gt_T_cj_ci(2, 0, 2), expected_CA, atol=1e-9)
    np.testing.assert_allclose(enc.gt_T_cj_ci(0, 2, 0), np.linalg.inv(expected_CA), atol=1e-9)
    K = enc.robots[1].intrinsics
    assert (K.fx, K.fy, K.cx, K.cy, K.width, K.height) == (FX, FY, CX, CY, W, H)
    np.testing.assert_allclose(enc.robots[0].stamps_s[1] - enc.robots[0].stamps_s[0], 0.1, atol=1e-6)
    sync = setting.meta["load_report"]["sync"]["scene_s3"]
    assert sync["B"]["max_abs_s"] == pytest.approx(0.010, abs=1e-6)
    assert sync["C"]["max_abs_s"] == pytest.approx(0.005, abs=1e-6)
    assert enc.robots[0].image(2).shape == (H, W, 3)


def test_lidar_depth_lands_on_the_right_pixel(dataset: Path) -> None:
    setting = load_setting(_manifest(dataset, "encounters:\n  - {scene: s3, vehicles: [A, B]}\n"))
    rob = setting.encounters[0].robots[0]
    assert isinstance(rob.depth[0], LidarDepth)
    d = rob.depth_m(0)
    assert d.shape == (H, W) and d.dtype == np.float32
    # by hand: LiDAR point (11, 0.5, -0.2) -> ego at LiDAR time (+1 m fwd, +1.0/+1.8 mount) = world (13, 0.5, 1.6);
    # camera A at world (1.5, 0, 1.6): forward 11.5, left 0.5 -> camera x = -0.5, y = 0, z = 11.5
    u, v = int(round(FX * -0.5 / 11.5 + CX)), int(round(CY))
    assert d[v, u] == pytest.approx(11.5, abs=1e-5)  # nearer of the two returns on this ray (z-buffer min)
    assert np.count_nonzero(d) == 1  # the far twin shares the pixel; the point behind the camera is dropped
    # frames 1, 2 have empty sweeps -> all zero, not missing
    assert np.count_nonzero(rob.depth_m(1)) == 0
    assert rob.depth is not None and setting.encounters[0].robots[1].depth == [None, None, None]


def test_project_points_known_answer() -> None:
    K = np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]])
    pts = np.array([[0.0, 0.0, 2.0], [0.5, -0.2, 5.0], [0.4, -0.2, 4.0], [0.8, -0.4, 8.0],
                    [np.nan, 0, 1], [0, 0, -3.0], [100.0, 0, 1.0]])
    d = project_points(pts, np.eye(4), K, 100, 80)
    assert d[40, 50] == pytest.approx(2.0)  # on the optical axis
    assert d[36, 60] == pytest.approx(5.0)  # u = 0.5/5*100 + 50, v = -0.2/5*100 + 40
    assert d[35, 60] == pytest.approx(4.0)  # (0.4, -0.2, 4) and (0.8, -0.4, 8) share a pixel: nearer wins
    assert np.count_nonzero(d) == 3  # NaN, behind-camera and out-of-image points leave no trace


def test_auto_encounters_and_window(dataset: Path) -> None:
    setting = load_setting(_manifest(dataset, "lidar: null\n"))
    assert sorted(e.name for e in setting.encounters) == ["scene_s2", "scene_s3"]
    assert all(r.depth is None for e in setting.encounters for r in e.robots)
    setting = load_setting(_manifest(dataset, "encounters:\n  - {scene: s3, window_s: [0.05, null], name: late}\n"))
    assert setting.encounters[0].name == "late" and setting.encounters[0].n_steps == 2


def test_truncated_lidar_file_is_a_clear_error(tmp_path: Path) -> None:
    build_fixture(tmp_path / "data", lidar_points={0: LIDAR_PTS})
    lid = next((tmp_path / "data" / "sweeps" / "LIDAR_FRONT_CENTER_A").iterdir())
    lid.write_bytes(lid.read_bytes()[:-4])
    manifest = _manifest(tmp_path, "encounters:\n  - {scene: s3}\n")
    with pytest.raises(ManifestError, match="not a multiple of 5") as info:  # the frames a run checks when loading
        load_setting(manifest)
    assert str(lid) in str(info.value)
    rob = load_setting(manifest, frames=0).encounters[0].robots[0]  # not decoded: read lazily, refused when read
    with pytest.raises(SceneError, match="not a multiple of 5"):
        rob.depth_m(0)


@pytest.mark.parametrize("mutate, expect", [
    (lambda r: (r / "v1.0" / "ego_pose.json").unlink(), "ego_pose.json not found"),
    (lambda r: (r / "v1.0" / "sample.json").write_text("{not json"), "not valid JSON"),
    (lambda r: _edit(r, "ego_pose", 0, rotation=[0, 0, 0, 0]), "zero-norm"),
    (lambda r: _edit(r, "sample_data", 0, drop="filename"), "lacks field"),
    (lambda r: _edit(r, "calibrated_sensor", 0, camera_intrinsic=[[1, 2], [3, 4]]), "3x3"),
    (lambda r: next((r / "sweeps" / "CAM_FRONT_CENTER_B").iterdir()).unlink(), "image file not found"),
])
def test_bad_tables_name_file_and_field(tmp_path: Path, mutate, expect: str) -> None:
    build_fixture(tmp_path / "data")
    mutate(tmp_path / "data")
    with pytest.raises(ManifestError, match=expect) as info:
        load_setting(_manifest(tmp_path, "encounters:\n  - {scene: s3}\n"))
    assert any(".json" in p.file or "sweeps" in p.file for p in info.value.problems)


def test_unknown_scene_vehicle_and_sync_tolerance(tmp_path: Path) -> None:
    build_fixture(tmp_path / "data", camera_dt_us=160_000)
    with pytest.raises(ManifestError) as info:
        load_setting(_manifest(tmp_path, "encounters:\n  - {scene: nope}\n  - {scene: s3, vehicles: [A, Z]}\n"
                                         "  - {scene: s2}\n"))
    msgs = " | ".join(str(p) for p in info.value.problems)
    assert "no scene named 'nope'" in msgs and "CAM_FRONT_CENTER_Z" in msgs and "no time steps" in msgs
    assert "encounters[0].scene" in msgs and "encounters[1].vehicles" in msgs


def _edit(root: Path, table: str, k: int, drop: str | None = None, **kw) -> None:
    p = root / "v1.0" / f"{table}.json"
    rows = json.loads(p.read_text())
    rows[k].update(kw)
    if drop:
        rows[k].pop(drop)
    p.write_text(json.dumps(rows))
