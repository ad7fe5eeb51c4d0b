"""Builders of tiny on-disk datasets for the dataset tests (plus a check of the builders themselves)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import yaml

from cerpe.geometry import make_se3, matrix_to_quat_xyzw, so3_exp

W, H = 32, 24
CAMERA = {"width": W, "height": H, "fx": 30.0, "fy": 31.0, "cx": 15.5, "cy": 11.5, "distortion": [0.0] * 5}
T_BODY_CAM = make_se3(so3_exp([0.1, -0.2, 0.3]), [0.05, -0.02, 0.1])
SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def body_pose(robot: int, t: float) -> np.ndarray:
    """Smooth ground-truth body pose of robot ``robot`` at time ``t`` (s since the start)."""
    return make_se3(so3_exp([0.0, 0.0, 0.4 * t + robot]), [t + 3 * robot, 0.5 * t, 0.1 * robot])


def write_trajectory(path: Path, fmt: str, stamps: np.ndarray, T: np.ndarray) -> None:
    q = matrix_to_quat_xyzw(T[:, :3, :3])
    t = T[:, :3, 3]
    if fmt == "tum":
        lines = ["# timestamp tx ty tz qx qy qz qw"] + [
            f"{s:.6f} {a[0]:.9f} {a[1]:.9f} {a[2]:.9f} {b[0]:.9f} {b[1]:.9f} {b[2]:.9f} {b[3]:.9f}"
            for s, a, b in zip(stamps, t, q)]
    elif fmt == "euroc":
        lines = ["#timestamp [ns], p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], v_x"] + [
            f"{int(round(s * 1e9))},{a[0]:.9f},{a[1]:.9f},{a[2]:.9f},{b[3]:.9f},{b[0]:.9f},{b[1]:.9f},{b[2]:.9f},0.0"
            for s, a, b in zip(stamps, t, q)]
    else:
        lines = ["stamp_s,tx,ty,tz,qx,qy,qz,qw,quality"] + [
            f"{s:.6f},{a[0]:.9f},{a[1]:.9f},{a[2]:.9f},{b[0]:.9f},{b[1]:.9f},{b[2]:.9f},{b[3]:.9f},1"
            for s, a, b in zip(stamps, t, q)]
    path.write_text("\n".join(lines) + "\n")


def write_mocap(root: Path, n_robots: int = 2, n_frames: int = 6, fmt: str = "tum", offset_s: float = 0.005,
                depth: bool = True, overlap: bool = True, interpolate: bool = True, t0: float = 1000.0) -> Path:
    """A mocap-layout dataset under ``root`` and its manifest; returns the manifest path.

    Robot r's images are at ``t0 + 0.1 k + r * offset_s``; ground truth is sampled
    at 50 Hz from :func:`body_pose` (so image stamps fall between samples);
    ``T_body_cam`` is :data:`T_BODY_CAM`; depth PNGs hold 2000 mm.
    """
    rng = np.random.default_rng(1)
    robots = []
    for r in range(n_robots):
        rd = root / "enc0" / f"r{r}"
        (rd / "rgb").mkdir(parents=True)
        stamps = t0 + 0.1 * np.arange(n_frames) + r * offset_s
        for s in stamps:
            cv2.imwrite(str(rd / "rgb" / f"{s:.6f}.png"), rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
        if depth:
            (rd / "depth").mkdir()
            for s in stamps:
                cv2.imwrite(str(rd / "depth" / f"{s:.6f}.png"), np.full((H, W), 2000, np.uint16))
        gt_t = t0 - 0.1 + np.arange(0, 0.1 * n_frames + 0.2, 0.02)
        write_trajectory(rd / "gt.txt", fmt, gt_t, np.stack([body_pose(r, s - t0) for s in gt_t]))
        (rd / "camera.yaml").write_text(yaml.safe_dump(CAMERA))
        rob = {"id": f"r{r}", "images": f"enc0/r{r}/rgb", "trajectory": f"enc0/r{r}/gt.txt",
               "trajectory_format": fmt, "intrinsics": f"enc0/r{r}/camera.yaml",
               "T_body_cam": T_BODY_CAM.tolist(), "interpolate": interpolate, "gt_tolerance_s": 0.011}
        if depth:
            rob.update(depth=f"enc0/r{r}/depth", depth_units_per_m=1000)
        robots.append(rob)
    enc = {"name": "enc0", "robots": robots}
    if overlap:
        ov = np.tile((np.arange(n_frames) / n_frames)[:, None, None], (1, n_robots, n_robots))
        np.save(root / "enc0" / "overlap.npy", ov)
        enc["overlap"] = "enc0/overlap.npy"
    manifest = {"name": "mocap-fixture", "adapter": "mocap", "enabled": True, "data_root": ".",
                "metric_depth": "sensor", "sync_tolerance_s": 0.02, "evaluation": {"every": 1}, "encounters": [enc]}
    path = root / "manifest.yaml"
    path.write_text(yaml.safe_dump(manifest, sort_keys=False))
    return path


def test_builder_writes_what_it_says(tmp_path: Path) -> None:
    m = write_mocap(tmp_path)
    doc = yaml.safe_load(m.read_text())
    assert len(doc["encounters"][0]["robots"]) == 2
    assert len(list((tmp_path / "enc0" / "r1" / "rgb").glob("*.png"))) == 6
    assert np.load(tmp_path / "enc0" / "overlap.npy").shape == (6, 2, 2)
