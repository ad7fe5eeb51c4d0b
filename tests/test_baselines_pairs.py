"""Per-pair baselines: conventions on real frames (TUM fr3, when ../shared is present), failure handling."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cerpe.baselines import BaselineError, build_baseline
from cerpe.baselines.base import relative_pose_from_matches
from cerpe.geometry import e_pos, e_rot, gt_scale_translation, make_se3, paper_T_ij, se3_from_tq_xyzw, so3_exp
from cerpe.scene import CameraIntrinsics, load_rgb

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "tum-fr3-office"
K_TUM = CameraIntrinsics(535.4, 539.2, 320.1, 247.6, 640, 480)


def _tum_pair(a: int, b: int):
    if not DATA.is_dir():
        pytest.skip("../shared/data/tum-fr3-office not present")
    gt = {}
    for line in (DATA / "groundtruth.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            v = [float(x) for x in line.split()]
            gt[v[0]] = se3_from_tq_xyzw(v[1:4], v[4:8])
    imgs = sorted((DATA / "rgb").glob("*.png"))
    pose = lambda p: gt[min(gt, key=lambda s: abs(s - float(p.stem)))]
    return load_rgb(imgs[a]), load_rgb(imgs[b]), paper_T_ij(pose(imgs[a]), pose(imgs[b]))


def test_two_view_geometry_known_answer():
    """Synthetic points, two different cameras: recovers T_cj_ci (rotation exact, translation direction)."""
    rng = np.random.default_rng(0)
    K_i = CameraIntrinsics(500, 500, 320, 240, 640, 480)
    K_j = CameraIntrinsics(420, 430, 300, 250, 640, 480)
    for _ in range(5):
        # small rotation: both cameras see the same points
        T = make_se3(so3_exp(rng.normal(scale=0.2, size=3)), rng.normal(size=3))
        X_i = np.c_[rng.uniform(-2, 2, (300, 2)), rng.uniform(4, 8, 300)]
        X_j = X_i @ T[:3, :3].T + T[:3, 3]
        keep = X_j[:, 2] > 0.5
        u_i = X_i[keep] @ K_i.K.T
        u_j = X_j[keep] @ K_j.K.T
        est = relative_pose_from_matches(u_i[:, :2] / u_i[:, 2:], u_j[:, :2] / u_j[:, 2:], K_i, K_j,
                                         min_matches=15, min_inliers=15, ransac_px=1.0)
        assert est.ok, est.reason
        assert e_rot(est.T_cj_ci, T) < 1e-3
        assert np.linalg.norm(est.T_cj_ci[:3, 3]) == pytest.approx(1.0)
        assert e_pos(gt_scale_translation(est.T_cj_ci[:3, 3], T[:3, 3]), T[:3, 3]) < 1e-2 * np.linalg.norm(T[:3, 3])


def test_too_few_matches_is_a_failure_not_an_error():
    K = CameraIntrinsics(500, 500, 320, 240, 640, 480)
    est = relative_pose_from_matches(np.zeros((4, 2)), np.zeros((4, 2)), K, K,
                                     min_matches=15, min_inliers=15, ransac_px=1.0)
    assert not est.ok and est.reason.startswith("too-few-matches")


def test_sift_textureless_pair_fails_cleanly():
    bl = build_baseline("sift-ransac")
    flat = np.full((120, 160, 3), 128, np.uint8)
    K = CameraIntrinsics(100, 100, 80, 60, 160, 120)
    est = bl.estimate(flat, K, flat, K)
    assert not est.ok and est.reason


def test_unknown_baseline_and_config():
    with pytest.raises(BaselineError, match="unknown baseline"):
        build_baseline("superglue")
    with pytest.raises(BaselineError, match="unknown config"):
        build_baseline("sift-ransac", ratoi=0.7)


def test_aliked_missing_or_truncated_weights(tmp_path):
    with pytest.raises(BaselineError, match="weight file not found"):
        build_baseline("aliked-lightglue", weights_dir=str(tmp_path))
    (tmp_path / "aliked-n16.pth").write_bytes(b"\x80\x02truncated")
    with pytest.raises(BaselineError, match="cannot read weight file"):
        build_baseline("aliked-lightglue", weights_dir=str(tmp_path))


@pytest.mark.shared_data
@pytest.mark.parametrize("name", ["sift-ransac", "aliked-lightglue"])
def test_real_pair_accuracy(name):
    img_i, img_j, T_gt = _tum_pair(1, 4)  # ~0.8 m apart, same desk
    est = build_baseline(name, max_keypoints=1024) if name == "aliked-lightglue" else build_baseline(name)
    r = est.estimate(img_i, K_TUM, img_j, K_TUM)
    assert r.ok, r.reason
    assert e_rot(r.T_cj_ci, T_gt) < 0.05
    t = T_gt[:3, 3]
    assert e_pos(gt_scale_translation(r.T_cj_ci[:3, 3], t), t) < 0.1 * np.linalg.norm(t)
    # the reverse direction is the inverse problem
    r2 = est.estimate(img_j, K_TUM, img_i, K_TUM)
    assert r2.ok and e_rot(r2.T_cj_ci, np.linalg.inv(T_gt)) < 0.05
