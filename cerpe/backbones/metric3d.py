"""Metric3Dv2 (Hu et al., TPAMI 2024) as a :class:`~cerpe.protocols.MetricDepthSource`.

The network predicts depth for a *canonical camera* (focal length 1000 px); the
canonical-camera transform both ways is implemented here as pure functions
(tested without the model), following the upstream ``hubconf.py`` recipe:

1. resize the image to fit ``616 x 1064`` (ViT models) keeping its aspect,
   ``scale = min(616/H, 1064/W)``, bilinear; scale the intrinsics alike;
2. pad (centred, ``pad_h // 2`` on top) with the ImageNet mean colour
   ``(123.675, 116.28, 103.53)``; normalise with the ImageNet mean/std (0..255);
3. predict canonical depth; remove the padding; upsample (bilinear) to the input size;
4. multiply by ``fx_scaled / 1000`` and clamp to ``0..300`` m.

The model itself comes from a local clone of YvanYin/Metric3D (its code needs
``mmengine`` or ``mmcv``): ``torch.hub.load(repo, 'metric3d_vit_small', source='local',
pretrain=False)`` plus the checkpoint's ``model_state_dict``. A ready ``model``
with Metric3D's ``inference({'input': x}) -> (depth, confidence, outputs)``
interface can be passed instead.

Metric3D needs the focal length: a frame with no intrinsics (neither the view's
nor the frame context's) gets no depth (``None``; counted in ``skipped``).
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from ..config import merge_conf
from ..protocols import FrameContext, View
from .weights import (
    PaperModelError,
    describe_key_mismatch,
    load_checkpoint,
    peak_vram_bytes,
    reset_peak_vram,
    select_device,
)

logger = logging.getLogger(__name__)

VIT_INPUT_HW = (616, 1064)
CANONICAL_FOCAL = 1000.0
MAX_DEPTH_M = 300.0
PAD_RGB = (123.675, 116.28, 103.53)
STD_RGB = (58.395, 57.12, 57.375)
HUB_MODELS = ("metric3d_vit_small", "metric3d_vit_large", "metric3d_vit_giant2")


class Metric3DError(PaperModelError):
    """Missing Metric3D clone/package/weights, a wrong checkpoint, or bad input."""


@dataclass(frozen=True)
class CanonicalInfo:
    """Bookkeeping of one canonical-camera input.

    Attributes:
        in_hw: original ``(H, W)``; scale: resize factor; resized_hw: after resizing;
        pad: ``(top, bottom, left, right)`` in the network input; fx_scaled: focal
        length of the resized image (pixels).
    """

    in_hw: tuple[int, int]
    scale: float
    resized_hw: tuple[int, int]
    pad: tuple[int, int, int, int]
    fx_scaled: float

    @property
    def depth_factor(self) -> float:
        """Canonical depth -> metric: ``fx_scaled / 1000``."""
        return self.fx_scaled / CANONICAL_FOCAL


def canonical_info(in_hw: tuple[int, int], fx: float, input_hw: tuple[int, int] = VIT_INPUT_HW) -> CanonicalInfo:
    """Sizes, padding and scaled focal for an ``in_hw`` image with focal ``fx`` (pixels)."""
    H, W = int(in_hw[0]), int(in_hw[1])
    if H <= 0 or W <= 0 or not np.isfinite(fx) or fx <= 0:
        raise Metric3DError(f"Metric3D input: need a non-empty image and fx > 0, got {W}x{H}, fx={fx}")
    scale = min(input_hw[0] / H, input_hw[1] / W)
    h, w = int(H * scale), int(W * scale)
    ph, pw = input_hw[0] - h, input_hw[1] - w
    return CanonicalInfo((H, W), scale, (h, w), (ph // 2, ph - ph // 2, pw // 2, pw - pw // 2), fx * scale)


def canonical_input(image: np.ndarray, info: CanonicalInfo) -> torch.Tensor:
    """``[H,W,3] uint8`` RGB -> ``[1,3,616,1064]`` normalised network input."""
    h, w = info.resized_hw
    rgb = cv2.resize(image, (w, h), interpolation=cv2.INTER_LINEAR)
    t, b, l, r = info.pad
    rgb = cv2.copyMakeBorder(rgb, t, b, l, r, cv2.BORDER_CONSTANT, value=PAD_RGB)
    x = torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1))).float()
    mean = torch.tensor(PAD_RGB).view(3, 1, 1)
    std = torch.tensor(STD_RGB).view(3, 1, 1)
    return ((x - mean) / std)[None]


def metric_from_canonical(pred: torch.Tensor | np.ndarray, info: CanonicalInfo) -> np.ndarray:
    """Canonical depth on the padded input ``[h_in,w_in]`` -> metric depth ``[H,W]`` float32 (m).

    Remove padding, upsample bilinearly to the original size, multiply by
    ``fx_scaled/1000``, clamp to ``0..300``.
    """
    p = torch.as_tensor(np.asarray(pred) if not isinstance(pred, torch.Tensor) else pred).float().squeeze()
    if p.ndim != 2:
        raise Metric3DError(f"Metric3D prediction: expected a single [H,W] map, got {tuple(p.shape)}")
    t, b, l, r = info.pad
    p = p[t:p.shape[0] - b, l:p.shape[1] - r]
    p = F.interpolate(p[None, None], size=info.in_hw, mode="bilinear", align_corners=False)[0, 0]
    return torch.clamp(p * info.depth_factor, 0.0, MAX_DEPTH_M).cpu().numpy().astype(np.float32)


def canonical_from_metric(depth_m: np.ndarray, info: CanonicalInfo, input_hw: tuple[int, int] = VIT_INPUT_HW
                          ) -> np.ndarray:
    """Metric depth ``[H,W]`` -> what a perfect network would predict on the padded input (inverse of the above).

    Resize to the resized size (bilinear), divide by ``fx_scaled/1000``, pad with 0.
    """
    h, w = info.resized_hw
    d = torch.as_tensor(np.asarray(depth_m, dtype=np.float32))[None, None]
    d = F.interpolate(d, size=(h, w), mode="bilinear", align_corners=False)[0, 0] / info.depth_factor
    t, b, l, r = info.pad
    return F.pad(d, (l, r, t, b)).numpy()


def _load_hub_model(repo: Path, name: str) -> torch.nn.Module:
    if name not in HUB_MODELS:
        raise Metric3DError(f"Metric3D model {name!r}: choose one of {', '.join(HUB_MODELS)}")
    if not (repo / "hubconf.py").is_file():
        raise Metric3DError(f"Metric3D: {repo} is not a clone of https://github.com/YvanYin/Metric3D "
                            f"(no hubconf.py); set metric3d.repo")
    try:
        return torch.hub.load(str(repo), name, source="local", pretrain=False)
    except ModuleNotFoundError as exc:
        raise Metric3DError(f"Metric3D code in {repo} needs a missing package ({exc}); "
                            f"pip install mmengine (see docs/PAPER_MODELS.md)") from None


def load_metric3d_weights(model: torch.nn.Module, path: Path) -> None:
    """Load ``model_state_dict`` (or a bare state dict) strictly enough to catch a wrong file.

    Upstream loads with ``strict=False``; we accept extra keys but no missing
    parameter, and report a few mismatches otherwise.
    """
    ckpt = load_checkpoint(path, "Metric3Dv2")
    sd = ckpt.get("model_state_dict", ckpt)
    sd = {k[len("module."):] if k.startswith("module.") else k: v for k, v in sd.items()}
    own = model.state_dict()
    missing = [k for k in own if k not in sd]
    if missing:
        raise Metric3DError(describe_key_mismatch(missing, [k for k in sd if k not in own], path, "Metric3Dv2"))
    bad = [k for k in own if tuple(sd[k].shape) != tuple(own[k].shape)]
    if bad:
        raise Metric3DError(f"{path}: Metric3Dv2 checkpoint of another model size? shapes differ for "
                            f"{', '.join(bad[:5])}; check metric3d.model")
    model.load_state_dict(sd, strict=False)


class Metric3DDepth:
    """:class:`~cerpe.protocols.MetricDepthSource` running Metric3Dv2 on the robot's own frame.

    Args:
        conf: see :attr:`default_conf` (``repo`` + ``checkpoint`` unless ``model`` given).
        model: a module with Metric3D's ``inference`` interface (tests).
    """

    name = "metric3d"
    # relative sigma of its depth's scale (MetricDepthSource.rel_sigma): an assumption, the order of a
    # monocular metric network's per-image scale error (the mono-sim simulation's is 9.4 %); not measured here
    rel_sigma = 0.1
    default_conf: dict[str, Any] = {
        "repo": None,
        "checkpoint": None,
        "model": "metric3d_vit_small",
        "device": "auto",
        "input_hw": VIT_INPUT_HW,
    }

    def __init__(self, conf: Mapping[str, Any] | None = None, model: torch.nn.Module | None = None) -> None:
        self.conf = merge_conf(self.default_conf, conf, "Metric3D conf")
        self.device = select_device(self.conf["device"])
        if model is None:
            if not self.conf["repo"] or not self.conf["checkpoint"]:
                raise Metric3DError("Metric3D: metric3d.repo (local clone) and metric3d.checkpoint are both "
                                    "required; see docs/PAPER_MODELS.md")
            model = _load_hub_model(Path(self.conf["repo"]).expanduser(), self.conf["model"])
            load_metric3d_weights(model, Path(self.conf["checkpoint"]).expanduser())
        self.model = model.eval().to(self.device)
        self.skipped = 0
        self.last_stats: dict[str, Any] = {}

    def depth_m(self, view: View, frame: FrameContext) -> np.ndarray | None:
        """Metric depth ``[H,W] float32`` (m) of the view; None without intrinsics."""
        K = view.intrinsics or frame.intrinsics
        if K is None:
            self.skipped += 1
            logger.warning("Metric3D: robot %s step %s has no intrinsics; no metric depth (skipped %d)",
                           frame.robot_id, frame.step, self.skipped)
            return None
        img = view.image
        if not isinstance(img, np.ndarray) or img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise Metric3DError(f"Metric3D: robot {frame.robot_id} step {frame.step}: expected [H,W,3] uint8 RGB")
        if (K.width, K.height) != (img.shape[1], img.shape[0]):
            # Intrinsics of another resolution: rescale the focal to this image.
            fx = K.fx * img.shape[1] / K.width
        else:
            fx = K.fx
        info = canonical_info(img.shape[:2], fx, tuple(self.conf["input_hw"]))
        t0 = time.perf_counter()
        reset_peak_vram(self.device)
        with torch.inference_mode():
            pred, _conf, _ = self.model.inference({"input": canonical_input(img, info).to(self.device)})
        depth = metric_from_canonical(pred, info)
        self.last_stats = {"seconds": time.perf_counter() - t0, "vram_peak_bytes": peak_vram_bytes(self.device)}
        return np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)


def build_metric3d(conf: Mapping[str, Any] | None = None) -> Metric3DDepth:
    """Factory used by :func:`cerpe.backbones.depth.build_depth_source` (``metric3d``)."""
    return Metric3DDepth(conf)
