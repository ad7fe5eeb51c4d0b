"""XFeat's network as the encoder runs it, in float32 or with its deeper convolutions in bfloat16.

The float32 network is kornia's, batch norms folded (:func:`cerpe.backbones.xfeat.fold_batchnorm`).
:class:`MixedPrecisionXFeat` runs the same weights with blocks 3 to 5 and the fusion block in
bfloat16 (oneDNN accumulates in float32). On a CPU with native bfloat16 (``avx512_bf16`` or AMX) those
blocks take about half the time: 640x480 on one thread, 34.4 -> 21.6 ms with every block in
bfloat16, about 8 ms less with these four. The first two blocks stay in float32: they read the grey
image at full and half resolution, and in bfloat16 they account for nearly all of the change to the
descriptors (mean ``1 - cos`` to the float32 map 1.4e-4 with every block, 2.0e-5 with these four).
The keypoint head reads the grey image and stays in float32, so its logits are the float32 ones bit for bit.

Precision is a choice of the run (``backbone.offline.precision``): the tables are made in float32,
so they do not depend on whether a CPU has bfloat16.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

logger = logging.getLogger(__name__)

__all__ = ["PRECISIONS", "BF16_BLOCKS", "native_bf16", "resolve_precision", "warn_if_emulated",
           "MixedPrecisionXFeat"]

#: ``fp32``; ``bf16``: :data:`BF16_BLOCKS` in bfloat16; ``auto``: bf16 where :func:`native_bf16`, else fp32
PRECISIONS = ("fp32", "bf16", "auto")
#: the blocks run in bfloat16 under ``bf16`` (the deeper ones: most of the work, little of the change)
BF16_BLOCKS = ("block3", "block4", "block5", "block_fusion")
# CPU flags (Linux /proc/cpuinfo) of instructions that compute bfloat16 products natively
_NATIVE_FLAGS = ("avx512_bf16", "amx_bf16")


def native_bf16(cpuinfo: str | Path = "/proc/cpuinfo") -> bool:
    """Whether the CPU computes bfloat16 natively (a flag of :data:`_NATIVE_FLAGS` in ``cpuinfo``).
    False where the file cannot be read (not Linux): bfloat16 without it can be slower than float32."""
    try:
        text = Path(cpuinfo).read_text(errors="replace")
    except OSError:
        return False
    for line in text.splitlines():
        if line.startswith("flags") and ":" in line:
            flags = set(line.split(":", 1)[1].split())
            return any(f in flags for f in _NATIVE_FLAGS)
    return False


def resolve_precision(precision: str, native: bool | None = None) -> str:
    """``fp32`` or ``bf16`` for a :data:`PRECISIONS` value (``auto``: ``bf16`` when ``native``,
    default :func:`native_bf16`); ValueError naming the known values otherwise. An explicit ``bf16``
    stays ``bf16`` (:func:`warn_if_emulated` says when that may be slow)."""
    if precision not in PRECISIONS:
        raise ValueError(f"XFeat precision {precision!r}: expected one of {', '.join(PRECISIONS)}")
    if precision != "auto":
        return precision
    return "bf16" if (native_bf16() if native is None else native) else "fp32"


def warn_if_emulated() -> None:
    """Log a warning, for a network about to run in ``bf16``, when the CPU has no native bfloat16
    (it may then be slower than fp32)."""
    if not native_bf16():
        logger.warning("XFeat precision bf16 on a CPU without native bfloat16 (no %s in /proc/cpuinfo): "
                       "it may run slower than fp32", " or ".join(_NATIVE_FLAGS))


class MixedPrecisionXFeat:
    """``net(x) -> (feats [1,64,H/8,W/8], keypoint logits [1,65,H/8,W/8], reliability [1,1,H/8,W/8])``,
    all float32, as kornia's ``XFeatModel.forward`` with :data:`BF16_BLOCKS` in bfloat16.

    ``net`` is the float32 network (folded, eval mode); it is kept and used for the other layers, and a
    bfloat16 copy of the listed blocks is made once. ``x``: ``[1,C,H,W]`` float32 in [0,1], H and W
    multiples of 32."""

    def __init__(self, net: Any) -> None:
        import torch

        self.net = net
        self.bf16 = {name: _bf16_copy(getattr(net, name)) for name in BF16_BLOCKS}
        self.dtype = torch.bfloat16

    def _block(self, name: str, x: Any) -> Any:
        if name in self.bf16:
            return self.bf16[name](x.to(self.dtype)).float()
        return getattr(self.net, name)(x)

    def __call__(self, x: Any) -> tuple[Any, Any, Any]:
        import torch.nn.functional as F

        net = self.net
        x = net.norm(x.mean(dim=1, keepdim=True))
        x1 = self._block("block1", x)
        x2 = self._block("block2", x1 + net.skip1(x))
        x3 = self._block("block3", x2)
        x4 = self._block("block4", x3)
        x5 = self._block("block5", x4)
        hw = (x3.shape[-2], x3.shape[-1])
        x4 = F.interpolate(x4, hw, mode="bilinear", align_corners=False)
        x5 = F.interpolate(x5, hw, mode="bilinear", align_corners=False)
        feats = self._block("block_fusion", x3 + x4 + x5)
        return feats, net.keypoint_head(net._unfold2d(x, ws=8)), net.heatmap_head(feats)


def _bf16_copy(module: Any) -> Any:
    import copy

    import torch

    return copy.deepcopy(module).to(torch.bfloat16).eval()
