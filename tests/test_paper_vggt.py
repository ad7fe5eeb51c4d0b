"""VGGT adapter: pose-encoding conversions, intrinsics, canvas bookkeeping; opt-in real model run."""
from __future__ import annotations

import numpy as np
import pytest

from cerpe.backbones.vggt import (
    CanvasGeometry,
    VGGTBackbone,
    VGGTError,
    canvas_geometry,
    decode_pose_encoding,
    encode_pose,
    intrinsics_to_input,
    map_to_input,
    render_canvas,
    unify_canvases,
)
from cerpe.geometry import (
    make_se3,
    matrix_to_quat_wxyz,
    quat_xyzw_to_matrix,
    random_se3,
    se3_inverse,
    so3_exp,
    wxyz_to_xyzw,
)
from cerpe.protocols import View


def _known_pose() -> np.ndarray:
    R = so3_exp(np.array([0.1, -0.4, 0.25]))
    return make_se3(R, np.array([0.3, -1.2, 2.5]))


def test_pose_encoding_decodes_known_pose_xyzw() -> None:
    T_cw = _known_pose()[None]
    K = np.array([[[400.0, 0, 259], [0, 380.0, 196], [0, 0, 1]]])
    enc = encode_pose(T_cw, K, (392, 518))
    # Layout: translation, quaternion XYZW (scalar last), fov_h, fov_w.
    assert np.allclose(enc[0, :3], [0.3, -1.2, 2.5])
    assert np.allclose(quat_xyzw_to_matrix(enc[0, 3:7]), T_cw[0, :3, :3], atol=1e-9)
    assert np.isclose(enc[0, 7], 2 * np.arctan(196 / 380.0))
    T_back, K_back = decode_pose_encoding(enc, (392, 518))
    assert np.allclose(T_back, T_cw, atol=1e-9)
    assert np.allclose(K_back[0, 0, 0], 400.0) and np.allclose(K_back[0, 1, 1], 380.0)
    assert np.allclose(K_back[0, :2, 2], [259.0, 196.0])  # canvas centre W/2, H/2


def test_pose_encoding_wxyz_source_and_sign() -> None:
    """A pose whose rotation arrives as WXYZ (nuScenes style) must be reordered; -q is the same rotation."""
    T_cw = _known_pose()
    q_wxyz = matrix_to_quat_wxyz(T_cw[:3, :3])
    enc = np.concatenate([T_cw[:3, 3], wxyz_to_xyzw(q_wxyz), [1.0, 1.2]])[None]
    assert np.allclose(decode_pose_encoding(enc, (100, 100))[0][0], T_cw, atol=1e-9)
    enc_neg = enc.copy()
    enc_neg[0, 3:7] *= -1.0
    assert np.allclose(decode_pose_encoding(enc_neg, (100, 100))[0][0], T_cw, atol=1e-9)
    # Feeding the scalar-first order unconverted gives a different rotation: the layout matters.
    enc_wrong = np.concatenate([T_cw[:3, 3], q_wxyz, [1.0, 1.2]])[None]
    assert not np.allclose(decode_pose_encoding(enc_wrong, (100, 100))[0][0], T_cw, atol=1e-3)
    # Unnormalised quaternions (raw head output) are normalised.
    enc_scaled = enc.copy()
    enc_scaled[0, 3:7] *= 3.0
    assert np.allclose(decode_pose_encoding(enc_scaled, (100, 100))[0][0], T_cw, atol=1e-9)


def test_pose_encoding_random_roundtrip_and_nan() -> None:
    rng = np.random.default_rng(0)
    T = np.stack([random_se3(rng) for _ in range(20)])
    K = np.tile(np.array([[300.0, 0, 259], [0, 310.0, 147], [0, 0, 1]]), (20, 1, 1))
    T_back, _ = decode_pose_encoding(encode_pose(T, K, (294, 518)), (294, 518))
    assert np.allclose(T_back, T, atol=1e-9)
    bad = encode_pose(T[:2], K[:2], (294, 518))
    bad[1, 0] = np.nan
    T_bad, _ = decode_pose_encoding(bad, (294, 518))
    assert np.isfinite(T_bad[0]).all() and np.isnan(T_bad[1]).all()
    with pytest.raises(VGGTError, match=r"\[S,9\]"):
        decode_pose_encoding(np.zeros((2, 8)), (10, 10))


def test_camera_from_world_to_camera_to_frame() -> None:
    """Frame 0 is the world: a point seen by camera 1 lands where camera 0 sees it."""
    T_c1_w = _known_pose()
    T_frame_c1 = se3_inverse(T_c1_w)
    p_w = np.array([0.5, 0.2, 4.0, 1.0])
    p_c1 = T_c1_w @ p_w
    assert np.allclose(T_frame_c1 @ p_c1, p_w)


def test_canvas_sizes_match_upstream_rules() -> None:
    g = canvas_geometry((480, 640), "crop")
    assert g.resized_hw == (392, 518) and g.net_hw == (392, 518) and g.crop_top == 0
    g = canvas_geometry((1000, 500), "crop")  # portrait: 518 x 1036 -> centre crop to 518
    assert g.resized_hw == (1036, 518) and g.crop_top == 259 and g.net_hw == (518, 518)
    g = canvas_geometry((480, 640), "pad")
    assert g.resized_hw == (392, 518) and g.net_hw == (518, 518) and (g.pad_top, g.pad_left) == (63, 0)
    g = canvas_geometry((640, 480), "pad")
    assert g.resized_hw == (518, 392) and (g.pad_top, g.pad_left) == (0, 63)
    with pytest.raises(VGGTError, match="mode"):
        canvas_geometry((10, 10), "stretch")


def test_pixel_bookkeeping_maps_back() -> None:
    for in_hw, mode in (((480, 640), "crop"), ((1000, 500), "crop"), ((640, 480), "pad")):
        g = canvas_geometry(in_hw, mode)
        u = np.array([0.0, 100.0, in_hw[1] - 1.0])
        v = np.array([0.0, 300.0, in_hw[0] - 1.0])
        un, vn = g.net_from_input(u, v)
        ub, vb = g.input_from_net(un, vn)
        assert np.allclose(ub, u) and np.allclose(vb, v)
    # Known answer: 640x480 crop -> x scale 518/640, y scale 392/480.
    g = canvas_geometry((480, 640), "crop")
    un, vn = g.net_from_input(np.array([319.5]), np.array([239.5]))
    assert np.allclose(un, 258.5) and np.allclose(vn, 195.5)  # centre -> canvas centre


def test_depth_map_back_to_input_with_crop() -> None:
    """Depth encoding the canvas coordinate comes back as the input pixel's canvas coordinate."""
    g = canvas_geometry((1000, 500), "crop")
    Hn, Wn = g.net_hw
    net = np.tile(np.arange(Hn, dtype=np.float32)[:, None] + 1.0, (1, Wn))  # depth = row + 1
    d = map_to_input(net, g)
    assert d.shape == (1000, 500)
    v = np.arange(1000)
    _, vn = g.net_from_input(np.zeros(1000), v)
    inside = (vn >= -0.5) & (vn <= Hn - 0.5)
    assert np.all(d[~inside] == 0.0)  # cropped rows: unknown
    core = inside & (vn >= 0) & (vn <= Hn - 1)
    assert np.allclose(d[core, 10], vn[core] + 1.0, atol=1e-3)


def test_render_canvas_places_image() -> None:
    img = np.zeros((60, 80, 3), np.uint8)
    img[:, :40] = 255
    g = unify_canvases([canvas_geometry((60, 80), "pad", 112), canvas_geometry((80, 60), "pad", 112)])[0]
    c = render_canvas(img, g)
    assert c.shape == (3, 112, 112)
    assert np.allclose(c[:, :g.pad_top], 1.0)  # white padding
    assert c[:, g.pad_top + 5, 80].max() < 0.05  # right half of the image is black


def test_intrinsics_to_input_known() -> None:
    g = canvas_geometry((480, 640), "crop")
    K_net = np.array([[404.0, 0, 259.0], [0, 396.9, 196.0], [0, 0, 1]])
    K = intrinsics_to_input(K_net, g)
    assert np.isclose(K.fx, 404.0 * 640 / 518) and np.isclose(K.fy, 396.9 * 480 / 392)
    assert np.isclose(K.cx, 319.5) and np.isclose(K.cy, 239.5)  # image centre, pixel centres at integers
    assert (K.width, K.height) == (640, 480)


def test_backbone_rejects_bad_views() -> None:
    torch = pytest.importorskip("torch")
    bb = VGGTBackbone({"device": "cpu"}, model=torch.nn.Identity())
    with pytest.raises(VGGTError, match="at least one"):
        bb.infer([])
    with pytest.raises(VGGTError, match="uint8"):
        bb.infer([View("a", np.zeros((10, 10, 3), np.float32))])
    with pytest.raises(VGGTError, match="no checkpoint"):
        VGGTBackbone({"device": "cpu"})


# ----------------------------------------------------------------------------- opt-in: real VGGT code
def _small_vggt():
    pytest.importorskip("vggt", reason="upstream vggt not importable (PYTHONPATH=/path/to/vggt)")
    torch = pytest.importorskip("torch")
    try:
        from vggt.heads.camera_head import CameraHead
        from vggt.heads.dpt_head import DPTHead
        from vggt.models.aggregator import Aggregator
        from vggt.models.vggt import VGGT
    except ImportError as exc:  # e.g. huggingface_hub / einops missing
        pytest.skip(f"vggt model code not importable: {exc}")
    torch.manual_seed(0)
    # The real VGGT class and forward; a small random-weight configuration of its
    # parts (the constructor only exposes embed_dim and always builds a ViT-L).
    model = VGGT.__new__(VGGT)
    torch.nn.Module.__init__(model)
    model.aggregator = Aggregator(img_size=112, patch_size=14, embed_dim=32, depth=4, num_heads=2,
                                  patch_embed="conv", num_register_tokens=4)
    model.camera_head = CameraHead(dim_in=64, trunk_depth=1, num_heads=2)
    with torch.no_grad():  # random weights give fov <= 0 (relu); bias it to ~1 rad after 4 refinements
        model.camera_head.pose_branch.fc2.bias[7:9] = 0.25
    model.depth_head = DPTHead(dim_in=64, output_dim=2, activation="exp", conf_activation="expp1", features=16,
                               out_channels=[8, 16, 32, 32], intermediate_layer_idx=[0, 1, 2, 3])
    model.point_head = None
    model.track_head = None
    return model


@pytest.mark.optional_model
def test_real_vggt_small_through_adapter() -> None:
    model = _small_vggt()
    bb = VGGTBackbone({"device": "cpu", "target_size": 112}, model=model)
    rng = np.random.default_rng(0)
    views = [View(("r0", 0), rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)),
             View(("r0", -1), rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)),
             View(("r1", 0), rng.integers(0, 255, (64, 48, 3), dtype=np.uint8))]
    out = bb.infer(views)
    assert out.T_frame_cam.shape == (3, 4, 4) and out.valid.all()
    R = out.T_frame_cam[:, :3, :3]
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-4)
    for v, d, c, K in zip(views, out.depth, out.depth_conf, out.intrinsics):
        assert d.shape == v.image.shape[:2] and c.shape == d.shape and d.dtype == np.float32
        assert (d >= 0).all() and (d > 0).mean() > 0.5 and (c[d > 0] >= 1.0).all()  # expp1 conf >= 1
        assert K is not None and (K.width, K.height) == (v.image.shape[1], v.image.shape[0])
    assert {"vggt_forward", "vggt_preprocess"} <= set(out.timings_s)
    assert bb.last_stats["n_views"] == 3 and bb.last_stats["vram_peak_bytes"] is None  # CPU


@pytest.mark.optional_model
def test_real_vggt_small_algorithm1_end_to_end() -> None:
    torch = pytest.importorskip("torch")
    from cerpe.algorithm import AlgorithmConfig, Team
    from cerpe.backbones.depth import DatasetDepth
    from cerpe.backbones.salad_dinov2 import SaladDinoV2Descriptor, SaladDinoV2Model
    from cerpe.protocols import FrameContext

    model = _small_vggt()
    bb = VGGTBackbone({"device": "cpu", "target_size": 112}, model=model)
    torch.manual_seed(1)
    desc_model = SaladDinoV2Model({"embed_dim": 32, "depth": 1, "num_heads": 2},
                                  {"num_clusters": 4, "cluster_dim": 8, "token_dim": 8, "hidden_dim": 16})
    desc = SaladDinoV2Descriptor({"device": "cpu", "image_size": (56, 56)}, model=desc_model)
    # tau = -1: the gate always opens, so image replies and collaborator views go through VGGT.
    team = Team(["r0", "r1", "r2"], desc, bb, DatasetDepth(), AlgorithmConfig().override({"gate.tau": -1.0, "memory.delta_k": 1}))
    rng = np.random.default_rng(2)
    sources = []
    for step in range(2):
        imgs = [rng.integers(0, 255, (48, 64, 3), dtype=np.uint8) for _ in range(3)]
        ctx = [FrameContext(r, step, None, np.full((48, 64), 2.0, np.float32)) for r in ("r0", "r1", "r2")]
        res = team.step(imgs, ctx)
        sources += [p.source for p in res.pairs]
        assert len(res.pairs) == 6
        assert all(np.isfinite(r.T_odom_cam).all() for r in res.robots)
        assert all(np.isfinite(r.scale) and r.scale > 0 for r in res.robots)
    assert "direct" in sources
