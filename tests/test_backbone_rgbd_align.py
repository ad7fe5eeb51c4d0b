"""Dense RGB-D alignment: known answers on the ray-cast room of ``test_backbone_offline``
(from perturbed starts, photometric only, a moving object), refusals and bad input."""
from __future__ import annotations

import numpy as np
import pytest
from test_backbone_offline import K, Room, _blocks, pose

from cerpe import geometry as G
from cerpe.backbones.rgbd_align import RGBDAlignError, align_rgbd, grey_image
from cerpe.protocols import View

T_REF = pose((0, 0, 0))
T_CUR = pose((0.04, -0.01, 0.06), (0.3, -0.6, 0.2))
T_GT = G.se3_inverse(T_CUR) @ T_REF  # reference-camera points into the current camera


def _near_room(seed: int) -> Room:
    """The test room shrunk to 3 x 2.5 x 4 m: at 4-9 m a pixel spans two texels of the
    room's unfiltered texture, and the aliasing, not the aligner, would set the error."""
    room = Room(seed)
    room.planes = [
        (np.array([0, 1.0, 0]), 1.0, np.array([1.0, 0, 0]), np.array([0, 0, 1.0])),
        (np.array([0, 0, 1.0]), 4.0, np.array([1.0, 0, 0]), np.array([0, 1.0, 0])),
        (np.array([1.0, 0, 0]), -1.5, np.array([0, 0, 1.0]), np.array([0, 1.0, 0])),
        (np.array([1.0, 0, 0]), 1.5, np.array([0, 0, 1.0]), np.array([0, 1.0, 0])),
        (np.array([0, 1.0, 0]), -1.5, np.array([1.0, 0, 0]), np.array([0, 0, 1.0])),
    ]
    return room


@pytest.fixture(scope="module")
def pair():
    room = _near_room(3)
    img0, d0 = room.render(T_REF)
    img1, d1 = room.render(T_CUR)
    return img0, d0, img1, d1


def _errors(T: np.ndarray, T_gt: np.ndarray = T_GT) -> tuple[float, float]:
    return (float(np.linalg.norm(T[:3, 3] - T_gt[:3, 3])),
            float(np.degrees(G.rotation_angle(T[:3, :3].T @ T_gt[:3, :3]))))


def _perturbed(rng: np.random.Generator, metres: float, degrees: float) -> np.ndarray:
    P = G.make_se3(G.so3_exp(np.radians(degrees) * rng.normal(size=3) / np.sqrt(3)),
                   metres * rng.normal(size=3) / np.sqrt(3))
    return P @ T_GT


@pytest.mark.parametrize("use_depth", [True, False])
def test_recovers_the_pose_from_perturbed_starts(pair, use_depth):
    img0, d0, img1, d1 = pair
    rng = np.random.default_rng(1)
    for _ in range(3):
        T_init = _perturbed(rng, 0.015, 0.4)
        res = align_rgbd(img0, d0, img1, d1 if use_depth else None, K.K, K.K, T_init)
        assert res.ok, res.reason
        e_t, e_r = _errors(res.T_cur_ref)
        assert e_t < 1e-3 and e_r < 0.02, (e_t, e_r, _errors(T_init))
        assert res.cost < res.cost0
        assert res.n_pixels > 500 and res.inlier_ratio > 0.9


def test_an_exact_start_stays(pair):
    img0, d0, img1, d1 = pair
    res = align_rgbd(img0, d0, img1, d1, K.K, K.K, T_GT)
    assert res.change_m < 5e-4 and res.change_deg < 0.01
    assert _errors(res.T_cur_ref)[0] < 5e-4


def test_a_far_start_is_refused_and_returned_unchanged(pair):
    img0, d0, img1, d1 = pair
    T_init = G.make_se3(np.eye(3), np.array([0.4, 0.0, 0.0])) @ T_GT
    res = align_rgbd(img0, d0, img1, d1, K.K, K.K, T_init)
    assert not res.ok and res.reason
    np.testing.assert_array_equal(res.T_cur_ref, T_init)


@pytest.mark.parametrize("value", [0, 128])
def test_blank_images_are_refused_without_nan(value):
    img = np.full((K.height, K.width, 3), value, np.uint8)
    depth = np.full((K.height, K.width), 3.0, np.float32)
    res = align_rgbd(img, depth, img, depth, K.K, K.K, np.eye(4))
    assert np.all(np.isfinite(res.T_cur_ref))
    # a blank image says nothing; a flat depth fixes 3 of the 6 degrees of freedom
    assert not res.ok or res.change_m < 1e-3
    no_depth = align_rgbd(img, np.zeros_like(depth), img, None, K.K, K.K, np.eye(4))
    assert not no_depth.ok and no_depth.reason == "few-pixels"


def test_an_object_moving_with_the_camera_does_not_pull_the_pose():
    """A textured box covering a fifth of the image that keeps its place in the image (it
    moves with the camera): from a start a few millimetres off (what P3P gives) the robust
    weights keep the pose on the room, and the box's pixels are the outliers. (From 15 mm
    off it stops near 11 mm: the box is a second basin.)"""
    room = _near_room(4)
    img0, d0 = room.render(T_REF)
    img1, d1 = room.render(T_CUR)
    patch = _blocks(11, (110, 150), 5)
    img0, img1, d0, d1 = img0.copy(), img1.copy(), d0.copy(), d1.copy()
    for img, d in ((img0, d0), (img1, d1)):
        img[70:180, 90:240] = patch
        d[70:180, 90:240] = 1.8
    T_init = _perturbed(np.random.default_rng(2), 0.004, 0.1)
    res = align_rgbd(img0, d0, img1, d1, K.K, K.K, T_init)
    assert res.ok, res.reason
    assert _errors(res.T_cur_ref)[0] < 0.5 * _errors(T_init)[0]
    assert res.inlier_ratio < 0.95  # the box's pixels are the outliers
    exact = align_rgbd(img0, d0, img1, d1, K.K, K.K, T_GT)
    assert _errors(exact.T_cur_ref)[0] < 2e-4


def test_bad_input_names_the_field(pair):
    img0, d0, img1, d1 = pair
    with pytest.raises(RGBDAlignError, match="T_cur_ref"):
        align_rgbd(img0, d0, img1, d1, K.K, K.K, np.full((4, 4), np.nan))
    with pytest.raises(RGBDAlignError, match="K_ref"):
        align_rgbd(img0, d0, img1, d1, np.eye(2), K.K, T_GT)
    with pytest.raises(RGBDAlignError, match="reference depth"):
        align_rgbd(img0, d0[None], img1, d1, K.K, K.K, T_GT)
    with pytest.raises(RGBDAlignError, match="grey_image"):
        grey_image(np.zeros((2, 3, 4, 5)))


def test_depth_at_another_resolution_and_missing_pixels(pair):
    import cv2

    img0, d0, img1, d1 = pair
    half = cv2.resize(d0, (K.width // 2, K.height // 2), interpolation=cv2.INTER_NEAREST)
    holes = d1.copy()
    holes[::7, ::5] = 0.0
    holes[:20] = np.nan
    res = align_rgbd(img0, half, img1, holes, K.K, K.K, _perturbed(np.random.default_rng(3), 0.01, 0.3))
    assert res.ok, res.reason
    assert _errors(res.T_cur_ref)[0] < 2e-3


def test_backbone_refines_the_depth_prior_pose(pair):
    """The offline backbone with and without the dense step on the same pair: keypoints alone
    leave millimetres, every pixel leaves a fraction of one."""
    from cerpe.backbones.config import OfflineConfig
    from cerpe.backbones.offline import OfflineGeometryBackbone

    img0, d0, img1, d1 = pair
    views = [View(("d", 1), img1, K, depth_m=d1), View(("d", 0), img0, K, depth_m=d0)]
    err = {}
    for on in (False, True):
        bb = OfflineGeometryBackbone(OfflineConfig(dense={"refine": on}))
        out = bb.infer(views)
        assert out.valid.all(), out.reasons
        err[on] = _errors(out.T_frame_cam[1])[0]  # the pass frame is the current camera
        assert bb.counts["dense-refined"] == int(on)
    assert err[True] < 5e-4 and err[True] < err[False], err


def test_pyramids_kept_by_the_caller_give_the_same_result(pair):
    """A frame is the current view of one alignment and the reference of the next: pyramids the caller
    keeps (built once per image, read-only, the current one with or without its depth) give bit for
    bit what align_rgbd builds itself; one too shallow, or without the depth it needs, is refused."""
    from cerpe.backbones.rgbd_align import rgbd_pyramid

    img0, d0, img1, d1 = pair
    T_init = _perturbed(np.random.default_rng(2), 0.01, 0.3)
    ref = rgbd_pyramid(img0, d0, K.K, 3)
    assert [lv.grey.shape for lv in ref] == [(K.height, K.width), (K.height // 2, K.width // 2),
                                             (K.height // 4, K.width // 4)]
    assert all(not a.flags.writeable for lv in ref for a in (lv.grey, lv.blurred, lv.depth_m, lv.K))
    for use_depth in (True, False):
        cur = rgbd_pyramid(img1, d1 if use_depth else None, K.K, 3)
        own = align_rgbd(img0, d0, img1, d1, K.K, K.K, T_init, levels=3, use_depth=use_depth)
        kept = align_rgbd(img0, d0, img1, d1, K.K, K.K, T_init, levels=3, use_depth=use_depth, pyramids=(ref, cur))
        assert own.ok and np.array_equal(own.T_cur_ref, kept.T_cur_ref) and own.iterations == kept.iterations
        assert (own.cost0, own.cost, own.n_pixels) == (kept.cost0, kept.cost, kept.n_pixels)
    with pytest.raises(RGBDAlignError, match="levels deep"):
        align_rgbd(img0, d0, img1, d1, K.K, K.K, T_init, levels=3, pyramids=(ref[:2], ref[:2]))
    with pytest.raises(RGBDAlignError, match="with depth"):
        align_rgbd(img0, d0, img1, d1, K.K, K.K, T_init, levels=3, pyramids=(ref, cur))  # cur: no depth
