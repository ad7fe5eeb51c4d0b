"""The paper's place-recognition descriptor: DINOv2 ViT-B/14 + trained SALAD head.

Implements :class:`cerpe.protocols.DescriptorEncoder` with the official SALAD
model (serizba/salad, ``dino_salad.ckpt``). The pipeline:

1. resize the image to 322x322 (bilinear, antialiased, aspect not kept, as SALAD's
   evaluation does), then ImageNet normalisation;
2. DINOv2 ViT-B/14 (all 12 blocks, final LayerNorm) -> patch tokens ``[B,768,23,23]``
   + CLS ``[B,768]``;
3. :class:`~cerpe.backbones.salad.SALADHead` -> ``[8448]`` float32, L2-normalised
   (64 clusters x 128 + 256-d token).

Checkpoint layout (upstream ``VPRModel``): ``backbone.model.<dinov2 hub key>``
and ``aggregator.<SALAD key>``, either at the top level (the released file) or
under ``state_dict`` (a Lightning checkpoint of your own training);
:func:`split_salad_state_dict` maps them and reports what does not fit.

Thresholds (``thresholds``): the paper's ``tau = 0.2`` (gate), ``tau_m = 0.9``,
``tau_k = 0.2`` (memory), stated for this descriptor.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..config import merge_conf
from ..protocols import View
from .dinov2 import DinoVisionTransformer
from .weights import (
    PaperModelError,
    describe_key_mismatch,
    load_checkpoint,
    load_state_dict_strict,
    select_device,
)
from .salad import SALADHead

logger = logging.getLogger(__name__)

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

BACKBONE_PREFIX = "backbone.model."
AGGREGATOR_PREFIX = "aggregator."


class SaladDinoV2Error(PaperModelError):
    """Bad input to, or a wrong checkpoint for, the SALAD/DINOv2 descriptor."""


def preprocess_salad(images: Sequence[np.ndarray], size_hw: tuple[int, int] = (322, 322)) -> torch.Tensor:
    """``[H,W,3] uint8`` RGB images -> ``[B,3,h,w]`` float32, resized and ImageNet-normalised.

    Resizing is bilinear with antialiasing (torchvision's ``Resize`` on PIL
    images, which SALAD's evaluation uses, antialiases too).
    """
    out = []
    for i, img in enumerate(images):
        if not isinstance(img, np.ndarray) or img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            desc = (f"{img.shape} {img.dtype}" if isinstance(img, np.ndarray) else type(img).__name__)
            raise SaladDinoV2Error(f"SALAD input image {i}: expected [H,W,3] uint8 RGB, got {desc}")
        t = torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1)[None].float() / 255.0
        t = F.interpolate(t, size=size_hw, mode="bilinear", align_corners=False, antialias=True)
        out.append(t[0])
    x = torch.stack(out)
    mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    return (x - mean) / std


def split_salad_state_dict(ckpt: Mapping[str, Any], path: Path | str = "<checkpoint>"
                           ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """Official SALAD checkpoint -> ``(dinov2_state, head_state)``.

    Accepts the released file (keys at the top level) and Lightning files
    (``{"state_dict": {...}}``); strips ``backbone.model.`` and ``aggregator.``.

    Raises:
        SaladDinoV2Error: keys of neither part are present (not a SALAD checkpoint),
            or other keys are present (listing a few).
    """
    sd = ckpt.get("state_dict", ckpt) if isinstance(ckpt, Mapping) else None
    if not isinstance(sd, Mapping):
        raise SaladDinoV2Error(f"{path}: no state dict found")
    backbone, head, other = {}, {}, []
    for k, v in sd.items():
        if k.startswith(BACKBONE_PREFIX):
            backbone[k[len(BACKBONE_PREFIX):]] = v
        elif k.startswith(AGGREGATOR_PREFIX):
            head[k[len(AGGREGATOR_PREFIX):]] = v
        else:
            other.append(k)
    if not backbone or not head:
        raise SaladDinoV2Error(describe_key_mismatch(
            [p + "*" for p, d in ((BACKBONE_PREFIX, backbone), (AGGREGATOR_PREFIX, head)) if not d],
            other, path, "SALAD/DINOv2"))
    if other:
        raise SaladDinoV2Error(describe_key_mismatch([], other, path, "SALAD/DINOv2"))
    return backbone, head


class SaladDinoV2Model(nn.Module):
    """DINOv2 backbone + SALAD head; ``forward([B,3,H,W] normalised) -> [B, 8448]``."""

    def __init__(self, dinov2_conf: Mapping[str, Any] | None = None, head_conf: Mapping[str, Any] | None = None) -> None:
        super().__init__()
        self.backbone = DinoVisionTransformer(**(dinov2_conf or {}))
        self.aggregator = SALADHead(**{"num_channels": self.backbone.embed_dim, **(head_conf or {})})

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        patches, cls = self.backbone.forward_tokens(x, norm=True)
        return self.aggregator(patches, cls)

    def load_salad_checkpoint(self, ckpt: Mapping[str, Any], path: Path | str = "<checkpoint>") -> None:
        """Load an official-layout checkpoint; mismatches raise :class:`SaladDinoV2Error`."""
        backbone_sd, head_sd = split_salad_state_dict(ckpt, path)
        try:
            load_state_dict_strict(self.backbone, backbone_sd, path, "SALAD DINOv2 backbone")
            load_state_dict_strict(self.aggregator, head_sd, path, "SALAD aggregator")
        except PaperModelError as exc:
            raise SaladDinoV2Error(str(exc)) from None


class SaladDinoV2Descriptor:
    """:class:`~cerpe.protocols.DescriptorEncoder` of the paper (8448-d SALAD/DINOv2).

    Args:
        conf: see :attr:`default_conf`; ``checkpoint`` is required unless a
            ``model`` is given.
        model: an already built :class:`SaladDinoV2Model` (tests, shared instances).
    """

    default_conf: dict[str, Any] = {
        "checkpoint": None,
        "device": "auto",
        "image_size": (322, 322),
        "dinov2": dict(DinoVisionTransformer.default_conf),  # preset dinov2_vitb14
        "head": {},  # SALADHead overrides; official: 64 clusters x 128 + 256
        "thresholds": {"tau": 0.2, "tau_m": 0.9, "tau_k": 0.2},
        "batch_size": 8,
    }

    def __init__(self, conf: Mapping[str, Any] | None = None, model: SaladDinoV2Model | None = None) -> None:
        self.conf = merge_conf(self.default_conf, conf, "SALAD/DINOv2 conf")
        self.device = select_device(self.conf["device"])
        if model is None:
            if not self.conf["checkpoint"]:
                raise SaladDinoV2Error("SALAD/DINOv2 descriptor: no checkpoint given (salad.checkpoint); "
                                       "see docs/PAPER_MODELS.md")
            path = Path(self.conf["checkpoint"]).expanduser()
            model = SaladDinoV2Model(self.conf["dinov2"], self.conf["head"])
            model.load_salad_checkpoint(load_checkpoint(path, "SALAD (DINOv2)"), path)
        self.model = model.eval().to(self.device)
        self.dim = int(self.model.aggregator.dim)
        self.thresholds = dict(self.conf["thresholds"])
        self.timings_s: dict[str, float] = {}

    @torch.inference_mode()
    def describe_batch(self, images: Sequence[np.ndarray]) -> np.ndarray:
        """``B`` images -> ``[B, dim]`` float32 unit-norm descriptors."""
        t0 = time.perf_counter()
        outs = []
        bs = max(1, int(self.conf["batch_size"]))
        for s in range(0, len(images), bs):
            x = preprocess_salad(images[s:s + bs], tuple(self.conf["image_size"])).to(self.device)
            outs.append(self.model(x).float().cpu())
        d = torch.cat(outs).numpy().astype(np.float32)
        self.timings_s = {"descriptor": time.perf_counter() - t0}
        if not np.all(np.isfinite(d)):
            raise SaladDinoV2Error("SALAD descriptor is not finite: corrupt weights?")
        return d

    def describe(self, view: View) -> np.ndarray:
        """One view -> ``[dim]`` float32, L2-normalised."""
        return self.describe_batch([view.image])[0]
