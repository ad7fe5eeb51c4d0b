"""The real frames in ../shared/data through tum-rgbd, frames and pairs (skipped when absent).

Every expected value is read here from the files themselves (README calibration,
groundtruth.txt, pose.txt, depth PNGs), not from the adapters' tables.
"""
from __future__ import annotations

import io
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from cerpe.datasets import LoadReport, ManifestError, load_manifest, load_setting
from cerpe.datasets.cli import check_one
from cerpe.geometry import rotation_angle, se3_from_tq_xyzw, se3_inverse
from test_datasets_fixtures import SHARED

REPO = Path(__file__).resolve().parents[1]
FR1 = SHARED / "tum-fr1-xyz-10"
SUN3D = SHARED / "sun3d-two-fragments"
pytestmark = [pytest.mark.shared_data, pytest.mark.skipif(not SHARED.is_dir(), reason="../shared/data not present")]


@pytest.fixture(autouse=True)
def _cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CERPE_CACHE", str(tmp_path / "cache"))


def fr1_readme_camera() -> tuple[np.ndarray, np.ndarray]:
    """K and distortion as the data folder's README states them."""
    text = (FR1 / "README.md").read_text()
    K = {k: float(re.search(rf"{k} (-?[\d.]+)", text).group(1)) for k in ("fx", "fy", "cx", "cy")}
    dist = [float(x) for x in re.search(r"p1,p2 =\s+([-\d. ]+)", text).group(1).split()]
    return np.array([[K["fx"], 0, K["cx"]], [0, K["fy"], K["cy"]], [0, 0, 1]]), np.array(dist)


def read_gt(path: Path) -> np.ndarray:
    rows = [ln.split() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    return np.array([[float(x) for x in r] for r in rows if r[0][0].isdigit()])


def test_tum_fr1_xyz_through_tum_rgbd(tmp_path: Path) -> None:
    m = tmp_path / "fr1.yaml"
    m.write_text(yaml.safe_dump({"name": "fr1", "adapter": "tum-rgbd", "data_root": str(FR1), "metric_depth": "dataset",
                                 "encounters": [{"name": "xyz", "robots": [
                                     {"id": "a", "sequence": ".", "camera": "fr1"},
                                     {"id": "b", "sequence": ".", "camera": "fr1", "reversed": True}]}]}))
    report = LoadReport()
    (enc,) = load_setting(m, report).encounters
    a = enc.robots[0]
    assert enc.n_steps == 9  # associate.py's greedy pairing leaves one of the 10 colour frames without depth
    assert report.counts[("xyz", "a: colour frames without depth within association_tolerance_s (dropped)")] == 1
    # intrinsics: the README's calibration, undistorted once with OpenCV (alpha 0: no black border)
    K, dist = fr1_readme_camera()
    newK, _ = cv2.getOptimalNewCameraMatrix(K, dist, (640, 480), 0.0, (640, 480))
    np.testing.assert_allclose(a.intrinsics.K, newK, atol=1e-9)
    assert (a.intrinsics.width, a.intrinsics.height) == (640, 480)
    maps = cv2.initUndistortRectifyMap(K, dist, None, newK, (640, 480), cv2.CV_32FC1)
    gt = read_gt(FR1 / "groundtruth.txt")
    for t in range(len(a)):
        rgb_stamp = float(a.frame_ids[t])
        depth_file = Path(a.depth[t].path)
        assert abs(float(depth_file.stem) - rgb_stamp) < 0.020  # association residual
        # depth in metres = the 16-bit file / 5000, undistorted with nearest neighbours
        raw = cv2.imread(str(depth_file), cv2.IMREAD_UNCHANGED).astype(np.float32) / 5000.0
        np.testing.assert_array_equal(a.depth_m(t), cv2.remap(raw, *maps, cv2.INTER_NEAREST))
        assert 0.3 < float(np.median(raw[raw > 0])) < 5.0
        # pose: groundtruth.txt interpolated to the colour stamp (100 Hz: translation linear, rotation near the rows)
        T = a.T_world_cam[t]
        t_exp = [np.interp(rgb_stamp, gt[:, 0], gt[:, k]) for k in (1, 2, 3)]
        np.testing.assert_allclose(T[:3, 3], t_exp, atol=1e-6)
        k = int(np.searchsorted(gt[:, 0], rgb_stamp))  # rows k-1, k bracket the stamp (10 ms apart)
        R0, R1 = (se3_from_tq_xyzw(gt[j, 1:4], gt[j, 4:8])[:3, :3] for j in (k - 1, k))
        a0, a1, a01 = (float(rotation_angle(X.T @ Y)) for X, Y in ((T[:3, :3], R0), (T[:3, :3], R1), (R0, R1)))
        assert a0 + a1 == pytest.approx(a01, abs=1e-6)  # on the geodesic between the two rows ...
        assert a0 / a01 == pytest.approx((rgb_stamp - gt[k - 1, 0]) / (gt[k, 0] - gt[k - 1, 0]), abs=1e-3)  # ... in time
        # colour: the file, undistorted bilinearly
        bgr = cv2.imread(str(FR1 / "rgb" / f"{a.frame_ids[t]}.png"), cv2.IMREAD_COLOR)
        np.testing.assert_array_equal(a.image(t), cv2.remap(bgr, *maps, cv2.INTER_LINEAR)[:, :, ::-1])
    np.testing.assert_allclose(enc.robots[1].T_world_cam, a.T_world_cam[::-1])
    assert enc.overlap is not None and np.nanmin(enc.overlap[:, 0, 1]) > 0.5  # 8 cm of motion: mostly co-visible


def _frames_manifest(tmp: Path) -> Path:
    m = tmp / "sun3d.yaml"
    m.write_text(yaml.safe_dump({"name": "sun3d", "adapter": "frames", "data_root": str(SUN3D), "metric_depth": "dataset",
                                 "intrinsics": "camera-intrinsics.txt", "rate_hz": 30, "encounters": [{"name": "f", "robots": [
                                     {"id": "f1", "folder": "fragment-1"}, {"id": "f2", "folder": "fragment-2"}]}]}))
    return m


def _reprojected_depth_error(rob, t0: int, t1: int) -> float:
    """Median |z - depth| of frame t0's points moved into frame t1 with the given poses (metres)."""
    K = rob.intrinsics
    d0, d1 = rob.depth_m(t0), rob.depth_m(t1)
    vv, uu = np.mgrid[0:480:8, 0:640:8]
    z = d0[vv, uu]
    ok = z > 0
    p = np.stack([(uu[ok] - K.cx) / K.fx * z[ok], (vv[ok] - K.cy) / K.fy * z[ok], z[ok], np.ones(ok.sum())])
    q = se3_inverse(rob.T_world_cam[t1]) @ rob.T_world_cam[t0] @ p
    u = np.rint(K.fx * q[0] / q[2] + K.cx).astype(int)
    v = np.rint(K.fy * q[1] / q[2] + K.cy).astype(int)
    inside = (q[2] > 0) & (u >= 0) & (u < 640) & (v >= 0) & (v < 480)
    d = d1[v[inside], u[inside]]
    return float(np.median(np.abs(q[2][inside][d > 0] - d[d > 0])))


def test_sun3d_fragments_through_frames(tmp_path: Path) -> None:
    (enc,) = load_setting(_frames_manifest(tmp_path)).encounters
    f1, f2 = enc.robots
    assert enc.robot_ids == ["f1", "f2"] and enc.n_steps == 50
    assert f1.frame_ids[0] == "fragment-1/frame-000935" and f2.frame_ids[-1] == "fragment-2/frame-003209"
    M = np.loadtxt(SUN3D / "camera-intrinsics.txt")
    assert (f1.intrinsics.fx, f1.intrinsics.fy, f1.intrinsics.cx, f1.intrinsics.cy) == (M[0, 0], M[1, 1], M[0, 2], M[1, 2])
    np.testing.assert_allclose(f2.stamps_s - f1.stamps_s, (3160 - 935) / 30.0)
    for rob, name in ((f1, "fragment-1"), (f2, "fragment-2")):
        rows = np.loadtxt(SUN3D / f"poses_c2w_{name}.txt", usecols=range(1, 13))
        np.testing.assert_allclose(rob.T_world_cam[:, :3, :], rows.reshape(-1, 3, 4), atol=1e-9)
        d = rob.depth_m(0)
        raw = cv2.imread(str(SUN3D / name / f"{rob.frame_ids[0].split('/')[1]}.depth.png"), cv2.IMREAD_UNCHANGED)
        np.testing.assert_allclose(d, np.where(raw == 65535, 0, raw) / 1000.0, rtol=1e-6)
        # the given poses and depth agree to a few cm (the README: 2-7 cm between frames 0 and 49)
        assert _reprojected_depth_error(rob, 0, 10) < 0.05 and _reprojected_depth_error(rob, 0, 49) < 0.08
    ov = enc.overlap
    assert ov is not None and ov.shape == (50, 2, 2) and np.isfinite(ov).all()
    assert 0.05 < ov[:, 0, 1].mean() < 0.8


def test_pair_list_written_for_real_frames(tmp_path: Path) -> None:
    """A SuperGlue-format list of a SUN3D cross-fragment pair and a TUM pair, read through `pairs`."""
    def c2w_sun3d(frag: str, n: int) -> np.ndarray:
        return np.loadtxt(SUN3D / frag / f"frame-{n:06d}.pose.txt")

    Ks = np.loadtxt(SUN3D / "camera-intrinsics.txt")
    T_s = se3_inverse(c2w_sun3d("fragment-2", 3160)) @ c2w_sun3d("fragment-1", 935)
    gt = read_gt(FR1 / "groundtruth.txt")
    rgb = sorted(p.stem for p in (FR1 / "rgb").glob("*.png"))
    T_tum = [se3_from_tq_xyzw(*np.split(gt[np.argmin(np.abs(gt[:, 0] - float(s))), 1:], [3])) for s in (rgb[0], rgb[9])]
    K_t, _ = fr1_readme_camera()
    T_t = se3_inverse(T_tum[1]) @ T_tum[0]

    def line(n0: str, n1: str, K0: np.ndarray, K1: np.ndarray, T: np.ndarray) -> str:
        return " ".join([n0, n1, "0", "0", *(f"{v:.10g}" for v in (*K0.ravel(), *K1.ravel(), *T.ravel()))])

    (tmp_path / "pairs.txt").write_text("\n".join([
        line("sun3d-two-fragments/fragment-1/frame-000935.color.png", "sun3d-two-fragments/fragment-2/frame-003160.color.png",
             Ks, Ks, T_s),
        line(f"tum-fr1-xyz-10/rgb/{rgb[0]}.png", f"tum-fr1-xyz-10/rgb/{rgb[9]}.png", K_t, K_t, T_t)]) + "\n")
    m = tmp_path / "pairs.yaml"
    m.write_text(yaml.safe_dump({"name": "real-pairs", "adapter": "pairs", "data_root": str(SHARED),
                                 "pairs": str(tmp_path / "pairs.txt"), "metric_depth": "dataset", "resize": [320, 240],
                                 "depth": {"replace": [[".color.png", ".depth.png"], ["/rgb/", "/depth/"]],
                                           "units_per_m": 1000}}))
    # TUM depth files have other stamps than the colour ones: the depth mapping does not reach them
    with pytest.raises(ManifestError) as info:
        load_setting(m)
    assert "depth file" in str(info.value) and "tum-fr1-xyz-10" in str(info.value)
    (tmp_path / "pairs.txt").write_text((tmp_path / "pairs.txt").read_text().splitlines()[0] + "\n")
    (enc,) = load_setting(m).encounters
    r0, r1 = enc.robots
    np.testing.assert_allclose(enc.gt_T_cj_ci(0, 0, 1), T_s, atol=1e-4)  # rotations printed with 6 digits
    assert r0.image(0).shape == (240, 320, 3) and r0.intrinsics.fx == pytest.approx(Ks[0, 0] / 2)
    raw = cv2.imread(str(SUN3D / "fragment-1" / "frame-000935.depth.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_allclose(r0.depth_m(0), cv2.resize(raw, (320, 240), interpolation=cv2.INTER_NEAREST) / 1000.0, rtol=1e-6)
    # the pair's co-visibility equals the frames adapter's at the same two frames (step 0 of the fragments),
    # up to the half-resolution grid
    (frames_enc,) = load_setting(_frames_manifest(tmp_path)).encounters
    np.testing.assert_allclose(enc.overlap[0], frames_enc.overlap[0], atol=0.02)  # 0.22 and 0.43 here
    # the TUM pair without depth loads with its ground truth
    (tmp_path / "pairs.txt").write_text(line(f"tum-fr1-xyz-10/rgb/{rgb[0]}.png", f"tum-fr1-xyz-10/rgb/{rgb[9]}.png",
                                             K_t, K_t, T_t) + "\n")
    doc = yaml.safe_load(m.read_text())
    del doc["depth"]
    m.write_text(yaml.safe_dump({**doc, "metric_depth": "none"}))
    (enc,) = load_setting(m).encounters
    np.testing.assert_allclose(enc.gt_T_cj_ci(0, 0, 1), T_t, atol=1e-9)


@pytest.mark.parametrize("name, adapter, steps", [("dev-tum-fr1-xyz", "tum-rgbd", 8),
                                                  ("dev-sun3d-two-fragments", "frames", 50),
                                                  ("dev-tum-fr3-office", "mocap", 8)])
def test_development_manifests_are_enabled_and_check(name: str, adapter: str, steps: int) -> None:
    path = REPO / "datasets_manifest" / f"{name}.yaml"
    man = load_manifest(path)
    assert man.enabled and man.enabled_if_present and man.adapter == adapter and man.name == name
    out = io.StringIO()
    assert check_one(str(path), 4, True, False, out=out) == []
    assert f"steps {steps}" in out.getvalue()
