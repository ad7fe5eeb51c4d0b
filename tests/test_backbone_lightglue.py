"""Learned matchers (LighterGlue over XFeat, ALIKED + LightGlue) with package weights: loading,
known-homography accuracy on real and drawn images, blank inputs, weight-file faults."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cerpe.backbones.lightglue import (AlikedExtractor, LightGlueError, LightGlueMatcher, empty_features,
                                       lightglue_state, xfeat_inputs)
from cerpe.backbones.xfeat import XFeatEncoder
from cerpe.scene import load_rgb

FR3 = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "tum-fr3-office" / "rgb"
# a view change a robot can see: rotation, shear, perspective
H_WARP = np.array([[0.9, 0.1, 30.0], [-0.08, 0.95, 20.0], [1e-4, -5e-5, 1.0]])


@pytest.fixture(scope="module")
def encoder() -> XFeatEncoder:
    return XFeatEncoder()


@pytest.fixture(scope="module")
def lighterglue() -> LightGlueMatcher:
    return LightGlueMatcher("xfeat")


@pytest.fixture(scope="module")
def aliked() -> tuple[AlikedExtractor, LightGlueMatcher]:
    return AlikedExtractor(max_keypoints=1024), LightGlueMatcher("aliked")


def drawn_image(seed: int = 0, hw: tuple[int, int] = (480, 640)) -> np.ndarray:
    """A cluttered RGB image of random rectangles, discs and lines (corners and blobs for detectors)."""
    import cv2

    rng = np.random.default_rng(seed)
    H, W = hw
    img = np.full((H, W, 3), 90, np.uint8)
    for _ in range(160):
        c = tuple(int(x) for x in rng.integers(0, 256, 3))
        x, y = int(rng.integers(0, W)), int(rng.integers(0, H))
        kind = rng.integers(3)
        if kind == 0:
            cv2.rectangle(img, (x, y), (x + int(rng.integers(8, 60)), y + int(rng.integers(8, 60))), c, -1)
        elif kind == 1:
            cv2.circle(img, (x, y), int(rng.integers(4, 25)), c, -1)
        else:
            cv2.line(img, (x, y), (int(rng.integers(0, W)), int(rng.integers(0, H))), c, int(rng.integers(1, 4)))
    return cv2.GaussianBlur(img, (3, 3), 0.8)


def _warp(img: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.warpPerspective(img, H_WARP, (img.shape[1], img.shape[0]))


def _reproj_err(f0: dict, f1: dict, m: np.ndarray) -> np.ndarray:
    import cv2

    p0 = f0["keypoints"][m[:, 0]].astype(np.float64)
    p1 = f1["keypoints"][m[:, 1]].astype(np.float64)
    return np.linalg.norm(cv2.perspectiveTransform(p0[:, None], H_WARP)[:, 0] - p1, axis=1)


def _images() -> list[tuple[str, np.ndarray]]:
    out = [("drawn", drawn_image())]
    if FR3.is_dir():
        out.append(("tum-fr3", load_rgb(sorted(FR3.glob("*.png"))[3])))
    return out


def test_weights_load_from_package_files(lighterglue, aliked):
    assert lighterglue.weights_path.name == "xfeat-lighterglue.pt" and lighterglue.weights_path.is_file()
    assert lighterglue.net.conf.n_layers == 6 and lighterglue.dim == 64
    ex, lg = aliked
    assert ex.weights_path.name == "aliked-n16.pth" and lg.weights_path.name == "aliked_lightglue.pth"
    assert lg.net.conf.n_layers == 9 and lg.dim == 128
    assert not lighterglue.net.training and not lg.net.training and not ex.net.training


@pytest.mark.parametrize("name,image", _images(), ids=[n for n, _ in _images()])
def test_xfeat_lighterglue_known_homography(encoder, lighterglue, name, image):
    f0 = xfeat_inputs(encoder.encode_image(image))
    f1 = xfeat_inputs(encoder.encode_image(_warp(image)))
    out = lighterglue({"image0": f0, "image1": f1})
    m = out["matches"]
    assert m.dtype == np.int64 and m.shape[1] == 2 and out["scores"].shape == (len(m),)
    assert len(m) >= 200, len(m)
    err = _reproj_err(f0, f1, m)
    assert np.mean(err < 3.0) > 0.9, (name, np.mean(err < 3.0))
    # each keypoint matched at most once, scores above the filter threshold
    assert len(np.unique(m[:, 0])) == len(m) and len(np.unique(m[:, 1])) == len(m)
    assert np.all(out["scores"] >= lighterglue.filter_threshold)


@pytest.mark.parametrize("name,image", _images(), ids=[n for n, _ in _images()])
def test_aliked_lightglue_known_homography(aliked, name, image):
    ex, lg = aliked
    f0, f1 = ex(image), ex(_warp(image))
    assert f0["descriptors"].shape == (len(f0["keypoints"]), 128) and f0["image_size"] == (640, 480)
    m = lg({"image0": f0, "image1": f1})["matches"]
    assert len(m) >= 200, len(m)
    assert np.mean(_reproj_err(f0, f1, m) < 3.0) > 0.9


def test_aliked_keypoints_are_in_input_pixels_when_downscaled():
    """Features of a 2x upscaled image extracted at half resolution land at 2x the pixels (+0.5 shift)."""
    import cv2

    img = drawn_image(3, (240, 320))
    big = cv2.resize(img, (640, 480), interpolation=cv2.INTER_NEAREST)
    small = AlikedExtractor(max_keypoints=256, max_side_px=320)
    f_big = small(big)
    f_ref = AlikedExtractor(max_keypoints=256, max_side_px=320)(img)
    assert f_big["image_size"] == (640, 480)
    # the downscaled (area) copy of big is img: same keypoints, mapped by x -> 2x + 0.5
    np.testing.assert_allclose(f_big["keypoints"], 2 * f_ref["keypoints"] + 0.5, atol=1e-3)


def test_max_keypoints_keeps_the_best_and_indexes_the_full_arrays(encoder):
    img = drawn_image(1)
    f0 = xfeat_inputs(encoder.encode_image(img))
    f1 = xfeat_inputs(encoder.encode_image(_warp(img)))
    capped = LightGlueMatcher("xfeat", max_keypoints=300)
    m = capped({"image0": f0, "image1": f1})["matches"]
    assert len(m) > 50
    top0 = set(np.argsort(-f0["scores"], kind="stable")[:300].tolist())
    top1 = set(np.argsort(-f1["scores"], kind="stable")[:300].tolist())
    assert set(m[:, 0].tolist()) <= top0 and set(m[:, 1].tolist()) <= top1
    assert np.mean(_reproj_err(f0, f1, m) < 3.0) > 0.9  # indices refer to the full arrays


def test_blank_and_empty_inputs_give_no_matches(encoder, lighterglue, aliked):
    ex, lg = aliked
    grey = np.full((480, 640, 3), 128, np.uint8)
    black = np.zeros((240, 320, 3), np.uint8)
    textured = drawn_image(2)
    for blank in (grey, black):
        fx = xfeat_inputs(encoder.encode_image(blank))
        assert len(fx["keypoints"]) == 0
        fa = ex(blank)
        assert len(fa["keypoints"]) == 0 and fa["descriptors"].shape == (0, 128)
        assert len(lighterglue({"image0": fx, "image1": fx})["matches"]) == 0
        assert len(lg({"image0": fa, "image1": ex(textured)})["matches"]) == 0
    # a few keypoints are not enough; empty features of the right width are accepted
    f = xfeat_inputs(encoder.encode_image(textured))
    few = {**f, "keypoints": f["keypoints"][:3], "descriptors": f["descriptors"][:3], "scores": f["scores"][:3]}
    assert lighterglue({"image0": few, "image1": f})["matches"].shape == (0, 2)
    assert lighterglue({"image0": empty_features((480, 640), 64), "image1": f})["matches"].shape == (0, 2)


def test_malformed_features_are_one_clear_error(lighterglue, aliked):
    ex, lg = aliked
    f = ex(drawn_image(4))
    with pytest.raises(LightGlueError, match=r"descriptors \[N,64\]"):
        lighterglue({"image0": f, "image1": f})  # ALIKED's 128-d descriptors into LighterGlue
    bad = {**f, "keypoints": f["keypoints"] + np.float32(700.0)}
    with pytest.raises(LightGlueError, match="outside the 640x480 image"):
        lg({"image0": bad, "image1": f})


def test_missing_truncated_and_mismatched_weight_files(tmp_path):
    missing = tmp_path / "none.pt"
    with pytest.raises(LightGlueError, match=f"weight file not found: {missing}"):
        LightGlueMatcher(weights=missing)
    trunc = tmp_path / "xfeat-lighterglue.pt"
    with open(_shipped("xfeat"), "rb") as fh:
        trunc.write_bytes(fh.read(4096))
    with pytest.raises(LightGlueError, match=f"cannot read weight file {trunc}"):
        LightGlueMatcher(weights=trunc)
    # the ALIKED LightGlue checkpoint does not fit LighterGlue's shapes
    with pytest.raises(LightGlueError, match="does not fit"):
        LightGlueMatcher("xfeat", weights=_shipped("aliked"))
    with pytest.raises(LightGlueError, match="weight file not found"):
        AlikedExtractor(weights_dir=tmp_path)


def _shipped(features: str) -> Path:
    from cerpe.backbones.lightglue import _FEATURES, package_file

    return package_file(_FEATURES[features]["package"], *_FEATURES[features]["file"])


def test_unknown_features_are_refused():
    with pytest.raises(LightGlueError, match="unknown features 'sift'"):
        LightGlueMatcher("sift")


def test_checkpoint_names_are_mapped():
    raw = {"extractor.model.net.x": 0, "matcher.self_attn.0.Wqkv.weight": 1, "matcher.cross_attn.1.to_out.bias": 2,
           "matcher.posenc.Wr.weight": 3}
    assert lightglue_state(raw, 2) == {"transformers.0.self_attn.Wqkv.weight": 1,
                                       "transformers.1.cross_attn.to_out.bias": 2, "posenc.Wr.weight": 3}
    plain = {"self_attn.0.a": 1, "log_assignment.0.b": 2}
    assert lightglue_state(plain, 1) == {"transformers.0.self_attn.a": 1, "log_assignment.0.b": 2}
