"""Metric3Dv2 canonical-camera transform: sizes, padding, de-canonicalisation, round trip."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from cerpe.backbones.metric3d import (
    CANONICAL_FOCAL,
    Metric3DDepth,
    Metric3DError,
    canonical_from_metric,
    canonical_info,
    canonical_input,
    metric_from_canonical,
)
from cerpe.protocols import FrameContext, View
from cerpe.scene import CameraIntrinsics


def test_canonical_info_known_values() -> None:
    info = canonical_info((480, 640), fx=500.0)
    assert np.isclose(info.scale, 616 / 480)
    assert info.resized_hw == (616, int(640 * 616 / 480))  # 821
    assert info.pad == (0, 0, 121, 122)
    assert np.isclose(info.fx_scaled, 500.0 * 616 / 480)
    assert np.isclose(info.depth_factor, info.fx_scaled / CANONICAL_FOCAL)
    wide = canonical_info((200, 1000), fx=300.0)  # width-limited
    assert np.isclose(wide.scale, 1.064) and wide.resized_hw == (212, 1064) and wide.pad == (202, 202, 0, 0)
    with pytest.raises(Metric3DError, match="fx > 0"):
        canonical_info((10, 10), fx=0.0)


def test_padding_is_mean_colour() -> None:
    img = np.full((480, 640, 3), 200, np.uint8)
    info = canonical_info(img.shape[:2], 500.0)
    x = canonical_input(img, info)
    assert x.shape == (1, 3, 616, 1064)
    # Mean colour, rounded to uint8 like upstream's cv2.copyMakeBorder on a uint8 image -> ~0.
    expected = (torch.tensor([124.0, 116.0, 104.0]) - torch.tensor([123.675, 116.28, 103.53])) / torch.tensor(
        [58.395, 57.12, 57.375])
    assert torch.allclose(x[0, :, :, :121], expected.view(3, 1, 1).expand(3, 616, 121), atol=1e-5)
    assert torch.allclose(x[0, 0, 300, 500], torch.tensor((200 - 123.675) / 58.395))


def test_metric_from_canonical_constant() -> None:
    info = canonical_info((480, 640), fx=500.0)
    pred = np.zeros((616, 1064), np.float32)
    t, b, l, r = info.pad
    pred[t:616 - b, l:1064 - r] = 10.0  # canonical 10 m
    d = metric_from_canonical(pred, info)
    assert d.shape == (480, 640)
    assert np.allclose(d, 10.0 * info.fx_scaled / 1000.0, atol=1e-4)


def test_roundtrip_smooth_depth_and_clamp() -> None:
    H, W = 120, 160
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    depth = (2.0 + 0.02 * u + 0.01 * v).astype(np.float32)
    info = canonical_info((H, W), fx=140.0)
    back = metric_from_canonical(canonical_from_metric(depth, info), info)
    inner = (slice(2, -2), slice(2, -2))  # borders see bilinear edge effects
    assert np.allclose(back[inner], depth[inner], rtol=1e-3)
    far = np.full((H, W), 1000.0, np.float32)
    assert np.allclose(metric_from_canonical(canonical_from_metric(far, info), info), 300.0)


class _CanonicalOracle(torch.nn.Module):
    """Test double with Metric3D's inference interface: returns the canonical depth of a known scene."""

    def __init__(self, canonical: np.ndarray) -> None:
        super().__init__()
        self.canonical = torch.from_numpy(canonical)

    def inference(self, data: dict) -> tuple:
        assert data["input"].shape == (1, 3, 616, 1064)
        return self.canonical[None, None], torch.ones_like(self.canonical)[None, None], {}


def test_depth_source_uses_intrinsics_and_skips_without() -> None:
    H, W = 96, 128
    K = CameraIntrinsics(110.0, 110.0, 63.5, 47.5, W, H)
    truth = np.full((H, W), 4.0, np.float32)
    info = canonical_info((H, W), K.fx)
    src = Metric3DDepth({"device": "cpu"}, model=_CanonicalOracle(canonical_from_metric(truth, info)))
    img = np.zeros((H, W, 3), np.uint8)
    d = src.depth_m(View("a", img, K), FrameContext("r0", 0, K))
    assert d.shape == (H, W) and np.allclose(d, 4.0, atol=1e-4)
    assert src.depth_m(View("b", img), FrameContext("r0", 1, None)) is None and src.skipped == 1
    with pytest.raises(Metric3DError, match="repo"):
        Metric3DDepth({"device": "cpu"})
