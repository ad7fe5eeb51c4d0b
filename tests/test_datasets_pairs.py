"""pairs adapter (SuperGlue / LoFTR pair lists): ground truth, rotations, resizing, bad lines."""
from __future__ import annotations

import io
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from cerpe.datasets import LoadReport, ManifestError, load_setting
from cerpe.datasets.cli import check_one
from cerpe.datasets.imageref import rot90_T
from cerpe.geometry import make_se3, se3_inverse, so3_exp

W, H = 64, 48
K0 = np.array([[50.0, 0, 31.5], [0, 52.0, 23.5], [0, 0, 1]])
K1 = np.array([[45.0, 0, 30.0], [0, 46.0, 24.0], [0, 0, 1]])
T_W_C0 = make_se3(so3_exp([0.1, -0.2, 0.05]), [0.3, -0.1, 0.2])
T_W_C1 = make_se3(so3_exp([-0.1, 0.3, 0.0]), [0.8, 0.1, 0.1])
X_W = np.array([0.5, 0.0, 2.5])  # a point both cameras see


@pytest.fixture(autouse=True)
def _cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CERPE_CACHE", str(tmp_path / "cache"))


def project(K: np.ndarray, T_w_c: np.ndarray, X: np.ndarray) -> np.ndarray:
    p = se3_inverse(T_w_c) @ np.append(X, 1.0)
    return (K @ (p[:3] / p[2]))[:2]


def blob_image(path: Path, uv: np.ndarray) -> None:
    img = np.zeros((H, W, 3), np.uint8)
    cv2.circle(img, (int(round(uv[0])), int(round(uv[1]))), 2, (255, 255, 255), -1)
    cv2.imwrite(str(path), img)


def centroid(img: np.ndarray) -> np.ndarray:
    vv, uu = np.nonzero(img[:, :, 0] > 100)
    return np.array([uu.mean(), vv.mean()])


def pair_line(n0: str, n1: str, rot0: int = 0, rot1: int = 0, extra: str = "") -> str:
    T_0to1 = se3_inverse(T_W_C1) @ T_W_C0
    nums = [rot0, rot1, *K0.ravel(), *K1.ravel(), *T_0to1.ravel()]
    return f"{n0} {n1} " + " ".join(f"{v:.12g}" for v in nums) + extra


def setup(tmp: Path, lines: list[str], **top) -> Path:
    (tmp / "img").mkdir(exist_ok=True)
    blob_image(tmp / "img" / "a.color.png", project(K0, T_W_C0, X_W))
    blob_image(tmp / "img" / "b.color.png", project(K1, T_W_C1, X_W))
    for name in ("a", "b"):
        cv2.imwrite(str(tmp / "img" / f"{name}.depth.png"), np.full((H, W), 2500, np.uint16))
    (tmp / "pairs.txt").write_text("# name0 name1 rot0 rot1 K0 K1 T_0to1\n" + "\n".join(lines) + "\n")
    m = tmp / "pairs.yaml"
    m.write_text(yaml.safe_dump({"name": "pairs-fixture", "adapter": "pairs", "data_root": ".", "pairs": "pairs.txt",
                                 "images": "img", "metric_depth": "none", **top}, sort_keys=False))
    return m


def test_pair_ground_truth_and_images(tmp_path: Path) -> None:
    m = setup(tmp_path, [pair_line("a.color.png", "b.color.png"), pair_line("b.color.png", "a.color.png")])
    s = load_setting(m)
    assert [e.name for e in s.encounters] == ["pair00000", "pair00001"]
    enc = s.encounters[0]
    assert enc.n_steps == 1 and enc.robot_ids == ["r0", "r1"] and enc.robots[0].frame_ids == ["a.color.png"]
    np.testing.assert_allclose(enc.gt_T_cj_ci(0, 0, 1), se3_inverse(T_W_C1) @ T_W_C0, atol=1e-9)  # = T_0to1
    for rob, K, T in zip(enc.robots, (K0, K1), (T_W_C0, T_W_C1)):
        np.testing.assert_allclose(rob.intrinsics.K, K)
        np.testing.assert_allclose(centroid(rob.image(0)), project(K, T, X_W), atol=0.6)
    assert enc.overlap is None  # no depth given


@pytest.mark.parametrize("rot0, rot1", [(1, 0), (2, 3), (3, 1)])
def test_rotations_keep_images_intrinsics_and_poses_consistent(tmp_path: Path, rot0: int, rot1: int) -> None:
    m = setup(tmp_path, [pair_line("a.color.png", "b.color.png", rot0, rot1)])
    (enc,) = load_setting(m).encounters
    T_c0_w = se3_inverse(T_W_C0)  # the adapter's world is camera 0 (before its rotation)
    X_0 = (T_c0_w @ np.append(X_W, 1.0))[:3]
    for rob, T, rot in zip(enc.robots, (T_W_C0, T_W_C1), (rot0, rot1)):
        img = rob.image(0)
        assert img.shape[:2] == ((W, H) if rot % 2 else (H, W)) and (rob.intrinsics.width, rob.intrinsics.height) == img.shape[1::-1]
        # the blob lies where the rotated camera (its intrinsics and its ground-truth pose) projects the point
        np.testing.assert_allclose(centroid(img), project(rob.intrinsics.K, rob.T_world_cam[0], X_0), atol=0.6)
        np.testing.assert_allclose(rob.T_world_cam[0] @ rot90_T(rot), T_c0_w @ T, atol=1e-9)


def test_resize_scales_intrinsics_and_depth(tmp_path: Path) -> None:
    m = setup(tmp_path, [pair_line("a.color.png", "b.color.png", 1, 0)], resize=[32, 24],
              depth={"replace": [[".color.", ".depth."]], "units_per_m": 1000}, metric_depth="dataset")
    (enc,) = load_setting(m).encounters
    r0, r1 = enc.robots
    assert r1.image(0).shape == (24, 32, 3) and r0.image(0).shape == (32, 24, 3)  # resized, then rotated
    assert r1.intrinsics.fx == pytest.approx(45.0 / 2) and r1.intrinsics.cx == pytest.approx((30.0 + 0.5) / 2 - 0.5)
    d = r0.depth_m(0)
    assert d.shape == (32, 24) and np.allclose(d, 2.5)
    assert enc.overlap is not None and 0.0 < enc.overlap[0, 0, 1] <= 1.0
    # longest side: 48 -> 64x48 becomes 48x36
    (tmp_path / "b").mkdir()
    m2 = setup(tmp_path / "b", [pair_line("a.color.png", "b.color.png")], resize=48)
    assert load_setting(m2).encounters[0].robots[0].image(0).shape == (36, 48, 3)


@pytest.mark.parametrize("line, field, text", [
    (pair_line("a.color.png", "b.color.png", extra=" 1"), "pairs line 3", "got 37 numbers"),
    (pair_line("a.color.png", "b.color.png").rsplit(" ", 1)[0], "pairs line 3", "got 35 numbers"),
    (pair_line("a.color.png", "b.color.png", 4, 0), "pairs line 3", "rot0/rot1"),
    (pair_line("a.color.png", "b.color.png").replace(" 50 ", " x ", 1), "pairs line 3", "not a number"),
    (pair_line("a.color.png", "missing.png"), "pairs line 3", "not found"),
])
def test_bad_pair_lines_name_the_line(tmp_path: Path, line: str, field: str, text: str) -> None:
    m = setup(tmp_path, [pair_line("a.color.png", "b.color.png"), line])
    with pytest.raises(ManifestError) as info:
        load_setting(m, LoadReport())
    (p,) = info.value.problems
    assert p.field == field and text in p.message, p
    assert p.file.endswith("pairs.txt") or p.file.endswith("missing.png")
    lines = check_one(str(m), None, True, False, out=io.StringIO())
    assert len(lines) == 1 and field in lines[0]


def test_pairs_manifest_schema(tmp_path: Path) -> None:
    m = setup(tmp_path, [pair_line("a.color.png", "b.color.png")], resize=[0, 5], max_pairs=0,
              depth={"replace": "x"}, encounters=[{"name": "x"}])
    with pytest.raises(ManifestError) as info:
        load_setting(m)
    assert {"resize", "max_pairs", "depth.replace", "depth.units_per_m", "encounters"} <= {p.field for p in info.value.problems}
    (tmp_path / "c").mkdir()
    m = setup(tmp_path / "c", [pair_line("a.color.png", "b.color.png")] * 3, max_pairs=2)
    assert len(load_setting(m).encounters) == 2
