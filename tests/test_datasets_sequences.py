"""tum-rgbd and frames adapters on generated folders: known answers, slices, undistortion, bad input."""
from __future__ import annotations

import io
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from cerpe.datasets import LoadReport, ManifestError, load_setting
from cerpe.datasets.cli import check_one
from cerpe.datasets.sequence import Frames, apply_slice
from cerpe.datasets.sync import associate
from cerpe.geometry import make_se3, matrix_to_quat_xyzw, so3_exp

W, H = 48, 36
CAM = {"width": W, "height": H, "fx": 40.0, "fy": 41.0, "cx": 23.5, "cy": 17.5}


@pytest.fixture(autouse=True)
def _cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CERPE_CACHE", str(tmp_path / "cache"))


def pose(t: float) -> np.ndarray:
    """Camera-to-world pose at time ``t`` (s): a slow turn and a drift along x."""
    return make_se3(so3_exp([0.0, 0.05 * t, 0.0]), [0.2 * t, 0.0, 0.0])


def write_tum(root: Path, n: int = 8, depth_shift_s: float = -0.012, camera: dict | None = None,
              depth_mm: float = 2000.0) -> Path:
    """A TUM RGB-D sequence folder: rgb/depth at 30 Hz (depth ``depth_shift_s`` apart), 100 Hz ground truth."""
    rng = np.random.default_rng(0)
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    stamps = 1000.0 + np.arange(n) / 30.0
    rgb_lines, depth_lines = ["# color images", "# timestamp filename"], ["# depth maps", "# timestamp filename"]
    for s in stamps:
        cv2.imwrite(str(root / "rgb" / f"{s:.6f}.png"), rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
        ds = s + depth_shift_s
        cv2.imwrite(str(root / "depth" / f"{ds:.6f}.png"), np.full((H, W), depth_mm * 5, np.uint16))
        rgb_lines.append(f"{s:.6f} rgb/{s:.6f}.png")
        depth_lines.append(f"{ds:.6f} depth/{ds:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    gt_t = np.arange(999.9, stamps[-1] + 0.1, 0.01)
    rows = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    for s in gt_t:
        T = pose(s - 1000.0)
        q = matrix_to_quat_xyzw(T[:3, :3])
        rows.append(f"{s:.4f} " + " ".join(f"{v:.9f}" for v in (*T[:3, 3], *q)))
    (root / "groundtruth.txt").write_text("\n".join(rows) + "\n")
    (root / "camera.yaml").write_text(yaml.safe_dump({**CAM, "distortion": [0.0] * 5, **(camera or {})}))
    return root


def tum_manifest(tmp: Path, robots: list[dict], **top) -> Path:
    p = tmp / "tum.yaml"
    p.write_text(yaml.safe_dump({"name": "tum-fixture", "adapter": "tum-rgbd", "data_root": ".", "metric_depth": "dataset",
                                 "encounters": [{"name": "e0", "robots": robots}], **top}, sort_keys=False))
    return p


def write_frames(folder: Path, numbers: range, depth_mm: int = 2000, t0: float = 0.0) -> None:
    """A 7-Scenes style folder: colour, 16-bit depth (mm; a 65535 hole) and 4x4 pose per frame."""
    rng = np.random.default_rng(1)
    folder.mkdir(parents=True)
    for n in numbers:
        cv2.imwrite(str(folder / f"frame-{n:06d}.color.png"), rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
        d = np.full((H, W), depth_mm, np.uint16)
        d[0, 0] = 65535
        cv2.imwrite(str(folder / f"frame-{n:06d}.depth.png"), d)
        np.savetxt(folder / f"frame-{n:06d}.pose.txt", pose(t0 + n / 30.0), fmt="%.9f")


def frames_manifest(tmp: Path, robots: list[dict], **top) -> Path:
    (tmp / "camera-intrinsics.txt").write_text(f"{CAM['fx']} 0 {CAM['cx']}\n0 {CAM['fy']} {CAM['cy']}\n0 0 1\n")
    p = tmp / "frames.yaml"
    p.write_text(yaml.safe_dump({"name": "frames-fixture", "adapter": "frames", "data_root": ".", "metric_depth": "dataset",
                                 "intrinsics": "camera-intrinsics.txt", "rate_hz": 30,
                                 "encounters": [{"name": "e0", "robots": robots}], **top}, sort_keys=False))
    return p


# --------------------------------------------------------------------------- association and slices
def test_associate_takes_closest_pairs_first_each_stamp_once() -> None:
    a = np.array([0.0, 0.10, 0.20, 0.30])
    b = np.array([0.005, 0.09, 0.095, 0.50])
    i, j = associate(a, b, 0.02)
    # 0.10 pairs with 0.095 (5 ms beats 10 ms); 0.09 is then left alone; 0.20 and 0.30 have nothing
    assert i.tolist() == [0, 1] and j.tolist() == [0, 2]
    i, j = associate(a, b, 0.02, offset_s=0.2)  # second stamps shifted by +0.2 s: 0.205 0.29 0.295 0.7
    assert i.tolist() == [2, 3] and j.tolist() == [0, 2]
    assert associate(a, b[:0], 0.02)[0].size == 0


def test_slices_window_stride_and_reverse() -> None:
    fr = Frames(np.arange(10.0), [f"i{k}" for k in range(10)], np.tile(np.eye(4), (10, 1, 1)), [str(k) for k in range(10)],
                [f"d{k}" for k in range(10)])
    out = apply_slice(fr, {"frames": [2, 9], "stride": 3}, "m", "r")
    assert out.frame_ids == ["2", "5", "8"] and out.depth == ["d2", "d5", "d8"]
    out = apply_slice(fr, {"frames": [-4, None], "reversed": True}, "m", "r")
    assert out.frame_ids == ["9", "8", "7", "6"]
    np.testing.assert_allclose(out.stamps_s, [6, 7, 8, 9])  # mirrored: still increasing, same span
    out = apply_slice(fr, {"window_s": [-3, None], "stride": 2}, "m", "r")
    assert out.frame_ids == ["6", "8"]
    with pytest.raises(ManifestError, match="empty"):
        apply_slice(fr, {"frames": [5, 5]}, "m", "r")


# --------------------------------------------------------------------------- tum-rgbd
def test_tum_reads_poses_depth_and_association(tmp_path: Path) -> None:
    write_tum(tmp_path / "seq")
    m = tum_manifest(tmp_path, [{"id": "a", "sequence": "seq", "camera": "seq/camera.yaml", "frames": [0, 4]},
                                {"id": "b", "sequence": "seq", "camera": "seq/camera.yaml", "frames": [4, 8]}])
    report = LoadReport()
    (enc,) = load_setting(m, report).encounters
    a, b = enc.robots
    assert enc.n_steps == 4 and a.frame_ids[0] == "1000.000000" and b.frame_ids[0] == f"{1000 + 4 / 30:.6f}"
    for rob in (a, b):
        for t in range(4):
            np.testing.assert_allclose(rob.T_world_cam[t], pose(rob.stamps_s[t] - 1000.0), atol=1e-5)  # interpolated
            assert abs(float(Path(rob.depth[t].path).stem) - rob.stamps_s[t]) < 0.02
            d = rob.depth_m(t)
            assert d.shape == (H, W) and np.allclose(d, 2.0)  # 10000 units / 5000 per metre
    K = a.intrinsics
    assert (K.fx, K.fy, K.cx, K.cy, K.width, K.height) == (40.0, 41.0, 23.5, 17.5, W, H)
    # ground-truth co-visibility from depth + poses (plane at 2 m, 0.1-0.3 m apart): high, and cached
    assert enc.overlap is not None and enc.overlap.shape == (4, 2, 2)
    assert np.all(enc.overlap[:, 0, 1] > 0.7) and np.all(enc.overlap[:, 0, 1] < 1.0)
    cached = list((tmp_path / "cache" / "covisibility" / "tum-fixture").glob("e0-*.npy"))
    assert len(cached) == 1 and np.array_equal(np.load(cached[0]), enc.overlap)
    assert load_setting(m).encounters[0].overlap is not None  # second load reads the cache (same key)
    assert len(list(cached[0].parent.iterdir())) == 1


def test_tum_covisibility_known_answer_and_off(tmp_path: Path) -> None:
    write_tum(tmp_path / "seq", n=31)  # one second: robot b 0.2 m to the side of a
    rob = {"sequence": "seq", "camera": "seq/camera.yaml"}
    m = tum_manifest(tmp_path, [{"id": "a", **rob, "frames": [0, 1]}, {"id": "b", **rob, "frames": [30, 31]}])
    ov = load_setting(m).encounters[0].overlap
    # Plane z = 2 m; b is 0.2 m along x and turned 0.05 rad about y. a's view spans x in [-1.2, 1.2] m,
    # b's x >= 0.2 + 2 tan(-atan(24/40) + 0.05) = -0.868 m. On the stride-4 grid (12 columns u = 0, 4, ..., 44):
    # a's columns with (u - 23.5) / 20 >= -0.868 are u >= 8 (10 of 12); b's columns whose ray meets the
    # plane at x <= 1.2 m are u <= 41.1 (11 of 12). Every row is the same.
    assert ov[0, 0, 1] == pytest.approx(10 / 12) and ov[0, 1, 0] == pytest.approx(11 / 12)
    m.write_text(m.read_text() + "covisibility: 'off'\n")
    assert load_setting(m).encounters[0].overlap is None


def test_tum_reversed_robot_plays_backwards(tmp_path: Path) -> None:
    write_tum(tmp_path / "seq")
    rob = {"sequence": "seq", "camera": "seq/camera.yaml"}
    (enc,) = load_setting(tum_manifest(tmp_path, [{"id": "f", **rob}, {"id": "r", **rob, "reversed": True}])).encounters
    f, r = enc.robots
    assert r.frame_ids == f.frame_ids[::-1]
    assert np.all(np.diff(r.stamps_s) > 0)
    np.testing.assert_allclose(r.T_world_cam, f.T_world_cam[::-1])


def test_tum_undistorts_with_adjusted_intrinsics(tmp_path: Path) -> None:
    dist = [-0.25, 0.08, 0.002, -0.001, 0.0]
    root = write_tum(tmp_path / "seq", n=2, camera={"width": 160, "height": 120, "fx": 120.0, "fy": 118.0,
                                                    "cx": 79.0, "cy": 61.0, "distortion": dist})
    K = np.array([[120.0, 0, 79.0], [0, 118.0, 61.0], [0, 0, 1]])
    X = np.array([[0.35, -0.2, 1.0]])  # a point seen off-centre, where distortion moves it by several pixels
    (ud, vd), = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, np.array(dist))[0][:, 0]
    img = np.zeros((120, 160, 3), np.uint8)
    cv2.circle(img, (int(round(ud)), int(round(vd))), 2, (255, 255, 255), -1)
    for p in (root / "rgb").iterdir():
        cv2.imwrite(str(p), img)
    for p in (root / "depth").iterdir():
        cv2.imwrite(str(p), np.full((120, 160), 10000, np.uint16))
    rob = {"sequence": "seq", "camera": "seq/camera.yaml"}
    (enc,) = load_setting(tum_manifest(tmp_path, [{"id": "a", **rob}, {"id": "b", **rob}])).encounters
    Kn = enc.robots[0].intrinsics
    newK, _ = cv2.getOptimalNewCameraMatrix(K, np.array(dist), (160, 120), 0.0, (160, 120))
    np.testing.assert_allclose([Kn.fx, Kn.fy, Kn.cx, Kn.cy], [newK[0, 0], newK[1, 1], newK[0, 2], newK[1, 2]])
    und = enc.robots[0].image(0)[:, :, 0].astype(float)
    vv, uu = np.nonzero(und > 128)
    u_exp, v_exp = Kn.fx * X[0, 0] / X[0, 2] + Kn.cx, Kn.fy * X[0, 1] / X[0, 2] + Kn.cy
    assert abs(uu.mean() - u_exp) < 0.7 and abs(vv.mean() - v_exp) < 0.7  # the blob moved where the pinhole model says
    assert abs(ud - u_exp) > 3  # ... which is not where it was
    d = enc.robots[0].depth_m(0)
    assert d.shape == (120, 160) and set(np.unique(d)) <= {0.0, 2.0}  # nearest-neighbour: no blended depth


def test_tum_named_camera_from_folder_name(tmp_path: Path) -> None:
    seq = tmp_path / "rgbd_dataset_freiburg3_fixture"
    write_tum(seq, n=2)
    for p in (seq / "rgb").iterdir():
        cv2.imwrite(str(p), np.zeros((480, 640, 3), np.uint8))
    for p in (seq / "depth").iterdir():
        cv2.imwrite(str(p), np.full((480, 640), 5000, np.uint16))
    rob = {"sequence": seq.name}
    (enc,) = load_setting(tum_manifest(tmp_path, [{"id": "a", **rob}, {"id": "b", **rob}])).encounters
    K = enc.robots[0].intrinsics  # fr3 has no distortion: the published values, unchanged
    assert (K.fx, K.fy, K.cx, K.cy, K.width, K.height) == (535.4, 539.2, 320.1, 247.6, 640, 480)
    assert isinstance(enc.robots[0].images[0], Path)


def _listed(seq: Path, kind: str, k: int) -> Path:
    """The k-th file listed in ``<kind>.txt`` (line k + 3: two comment lines first)."""
    rows = [ln.split() for ln in (seq / f"{kind}.txt").read_text().splitlines() if not ln.startswith("#")]
    return seq / rows[k][1]


def _tum_bad(tmp: Path, mutate) -> ManifestError:
    seq = write_tum(tmp / "seq")
    mutate(seq)
    rob = {"sequence": "seq", "camera": "seq/camera.yaml"}
    m = tum_manifest(tmp, [{"id": "a", **rob}, {"id": "b", **rob}])
    lines = check_one(str(m), None, True, False, out=io.StringIO())
    assert lines, "cerpe check must list the problem"
    with pytest.raises(ManifestError) as info:
        load_setting(m)
    assert not list((tmp / "cache").rglob("*.npy")), "nothing written for a setting that failed to load"
    return info.value


def test_tum_missing_rgb_txt(tmp_path: Path) -> None:
    err = _tum_bad(tmp_path, lambda seq: (seq / "rgb.txt").unlink())
    assert any(p.file.endswith("seq/rgb.txt") and "rgb.txt not found" in p.message for p in err.problems)


def test_tum_stamps_that_do_not_associate(tmp_path: Path) -> None:
    def shift(seq: Path) -> None:
        lines = (seq / "depth.txt").read_text().splitlines()
        out = [ln if ln.startswith("#") else f"{float(ln.split()[0]) + 5:.6f} {ln.split()[1]}" for ln in lines]
        (seq / "depth.txt").write_text("\n".join(out) + "\n")

    err = _tum_bad(tmp_path, shift)
    p = err.problems[0]  # one per robot (both read this sequence)
    assert len(err.problems) == 2 and p.file.endswith("seq/rgb.txt") and p.field.endswith("rgb.txt line 3")
    assert "depth.txt line 3" in p.message and "association_tolerance_s" in p.message


def test_tum_depth_of_another_size_names_the_line(tmp_path: Path) -> None:
    def shrink(seq: Path) -> None:
        cv2.imwrite(str(_listed(seq, "depth", 2)), np.full((H // 2, W // 2), 1000, np.uint16))

    err = _tum_bad(tmp_path, shrink)
    p = err.problems[0]
    assert "depth" in p.file and p.field.endswith("depth.txt line 5") and f"expected {W}x{H}" in p.message


def test_tum_8bit_depth_is_refused(tmp_path: Path) -> None:
    err = _tum_bad(tmp_path, lambda seq: cv2.imwrite(str(_listed(seq, "depth", 0)), np.ones((H, W), np.uint8)))
    assert "8-bit" in err.problems[0].message and err.problems[0].field.endswith("depth.txt line 3")


def test_tum_bad_camera_and_slices_are_schema_errors(tmp_path: Path) -> None:
    write_tum(tmp_path / "seq")
    m = tum_manifest(tmp_path, [{"id": "a", "sequence": "seq", "camera": "fr9", "stride": 0},
                                {"id": "a", "sequence": "seq", "reversed": "yes", "frames": [1.5, 2]}])
    with pytest.raises(ManifestError) as info:
        load_setting(m)
    fields = {p.field for p in info.value.problems}
    assert {"encounters[0].robots[0].camera", "encounters[0].robots[0].stride", "encounters[0].robots[1].id",
            "encounters[0].robots[1].reversed", "encounters[0].robots[1].frames"} <= fields
    m = tum_manifest(tmp_path, [{"id": "a", "sequence": "seq"}, {"id": "b", "sequence": "seq", "camera": "fr1"}])
    with pytest.raises(ManifestError, match="cannot tell the camera"):  # folder name "seq" names no camera
        load_setting(m)


# --------------------------------------------------------------------------- frames
def test_frames_reads_folders_as_robots(tmp_path: Path) -> None:
    write_frames(tmp_path / "seq-01", range(0, 10))
    write_frames(tmp_path / "seq-02", range(100, 106))
    m = frames_manifest(tmp_path, [{"id": "a", "folder": "seq-01", "stride": 2},
                                   {"id": "b", "folder": "seq-02", "reversed": True}])
    report = LoadReport()
    (enc,) = load_setting(m, report).encounters
    a, b = enc.robots
    assert enc.n_steps == 5 and report.counts[("e0", "frames beyond the shortest robot (dropped)")] == 1
    assert a.frame_ids == [f"seq-01/frame-{n:06d}" for n in (0, 2, 4, 6, 8)]
    assert b.frame_ids[0] == "seq-02/frame-000105"
    np.testing.assert_allclose(a.stamps_s, np.array([0, 2, 4, 6, 8]) / 30.0)
    for t in range(5):
        np.testing.assert_allclose(a.T_world_cam[t], pose(2 * t / 30.0), atol=1e-8)
    d = b.depth_m(0)
    assert d[0, 0] == 0.0 and np.allclose(d.ravel()[1:], 2.0)  # 65535 = no measurement; millimetres
    K = a.intrinsics
    assert (K.fx, K.fy, K.cx, K.cy, K.width, K.height) == (40.0, 41.0, 23.5, 17.5, W, H)
    assert enc.overlap is not None and np.isfinite(enc.overlap[:, 0, 1]).all()


def test_frames_inline_intrinsics_and_missing_pose(tmp_path: Path) -> None:
    write_frames(tmp_path / "s", range(4))
    (tmp_path / "s" / "frame-000001.pose.txt").unlink()
    m = frames_manifest(tmp_path, [{"id": "a", "folder": "s", "intrinsics": {"fx": 50, "fy": 50, "cx": 24, "cy": 18}},
                                   {"id": "b", "folder": "s", "depth": False}])
    report = LoadReport()
    (enc,) = load_setting(m, report).encounters
    assert enc.robots[0].intrinsics.fx == 50 and enc.robots[1].intrinsics.fx == 40
    assert not enc.robots[0].has_gt(1) and report.counts[("e0", "a: frames without ground-truth pose")] == 1
    assert enc.robots[1].depth is None and enc.overlap is None  # no depth for b: no co-visibility


@pytest.mark.parametrize("case", ["pose-3-rows", "pose-not-rigid", "depth-size", "depth-8bit", "no-frames", "bad-intrinsics"])
def test_frames_bad_input_names_file_and_line(tmp_path: Path, case: str) -> None:
    s = tmp_path / "s"
    write_frames(s, range(4))
    target = {"pose-3-rows": s / "frame-000002.pose.txt", "pose-not-rigid": s / "frame-000002.pose.txt",
              "depth-size": s / "frame-000001.depth.png", "depth-8bit": s / "frame-000001.depth.png",
              "no-frames": s, "bad-intrinsics": tmp_path / "camera-intrinsics.txt"}[case]
    m = frames_manifest(tmp_path, [{"id": "a", "folder": "s"}, {"id": "b", "folder": "s"}])
    if case == "pose-3-rows":
        target.write_text("\n".join(target.read_text().splitlines()[:3]) + "\n")
    elif case == "pose-not-rigid":
        np.savetxt(target, np.diag([2.0, 1, 1, 1]))
    elif case == "depth-size":
        cv2.imwrite(str(target), np.ones((H, W + 2), np.uint16))
    elif case == "depth-8bit":
        cv2.imwrite(str(target), np.ones((H, W), np.uint8))
    elif case == "no-frames":
        for p in s.glob("*.color.png"):
            p.unlink()
    else:
        target.write_text("40 0 23.5\n0 41 17.5\n")
    with pytest.raises(ManifestError) as info:
        load_setting(m)
    msg = "\n".join(map(str, info.value.problems))
    assert str(target) in msg, msg
    if case == "pose-3-rows":
        assert "frame-000002.pose.txt: encounters[0].robots[0].folder line 4: pose: 3 rows, expected a 4x4 matrix" in msg
    if case == "bad-intrinsics":
        assert "line 3" in msg
    assert check_one(str(m), None, True, False, out=io.StringIO())  # cerpe check lists it too, no traceback


def _enabled_copy(template: str, tmp: Path) -> Path:
    """A committed template with ``enabled: true`` (its data_root still from the environment)."""
    src = Path(__file__).resolve().parents[1] / "datasets_manifest" / template
    out = tmp / template
    out.write_text(src.read_text().replace("enabled: false", "enabled: true"))
    return out


def test_templates_load_once_their_root_is_filled(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("rgbd_dataset_freiburg1_desk", "rgbd_dataset_freiburg1_desk2"):
        seq = write_tum(tmp_path / "tum" / name, n=7)
        for kind, arr in (("rgb", np.zeros((480, 640, 3), np.uint8)), ("depth", np.full((480, 640), 9000, np.uint16))):
            for p in (seq / kind).iterdir():
                cv2.imwrite(str(p), arr)
    for seq, n in (("seq-01", 9), ("seq-02", 7)):  # 7-Scenes' 640x480 (the template's intrinsics are for it)
        write_frames(tmp_path / "7s" / "chess" / seq, range(n))
        for p in (tmp_path / "7s" / "chess" / seq).glob("*.png"):
            cv2.imwrite(str(p), np.zeros((480, 640, 3), np.uint8) if ".color." in p.name
                        else np.full((480, 640), 2000, np.uint16))
    monkeypatch.setenv("TUM_ROOT", str(tmp_path / "tum"))
    monkeypatch.setenv("SEVEN_SCENES_ROOT", str(tmp_path / "7s"))
    (enc,) = load_setting(_enabled_copy("tum-rgbd-desk.yaml", tmp_path)).encounters
    assert enc.robot_ids == ["desk", "desk2"] and enc.n_steps == 3  # 7 frames, stride 3
    assert enc.robots[0].intrinsics.width == 640 and enc.robots[0].intrinsics.fx != 517.3  # fr1, undistorted
    (enc,) = load_setting(_enabled_copy("seven-scenes-chess.yaml", tmp_path)).encounters
    assert enc.robot_ids == ["seq-01", "seq-02"] and enc.n_steps == 3
