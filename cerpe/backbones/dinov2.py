"""DINOv2 vision transformer (Oquab et al., 2023) in plain PyTorch.

Written from the public description and the state-dict layout of
facebookresearch/dinov2's torch-hub models (``dinov2_vit{s,b,l}14``), so their
``*_pretrain.pth`` files -- and the ``backbone.model.*`` part of a SALAD
checkpoint -- load into :class:`DinoVisionTransformer` with no missing or
unexpected keys. No torchvision, timm or xformers: attention is
``torch.nn.functional.scaled_dot_product_attention``.

State-dict names (hub layout, ``block_chunks=0``):
``cls_token [1,1,D]``, ``pos_embed [1,1+37*37,D]`` (trained at 518x518),
``mask_token [1,D]``, ``patch_embed.proj.{weight,bias}``,
``blocks.<i>.{norm1,norm2}.{weight,bias}``, ``blocks.<i>.attn.{qkv,proj}.{weight,bias}``,
``blocks.<i>.{ls1,ls2}.gamma``, ``blocks.<i>.mlp.{fc1,fc2}.{weight,bias}``,
``norm.{weight,bias}``; ``register_tokens`` only for the ``_reg`` variants.

Positional embeddings are resampled for other input sizes exactly as upstream
does (bicubic, no antialias, scale factor ``(h0 + 0.1)/37``), which matters for
SALAD's 322x322 input (23x23 patches).
"""
from __future__ import annotations

import math
from typing import Any

import torch
import torch.nn as nn
import torch.nn.functional as F

from ..config import merge_conf
from ..errors import CerpeError


class DinoV2Error(CerpeError, ValueError):
    """Bad DINOv2 configuration or input (unknown preset, size not a multiple of the patch)."""


#: Architecture presets of the hub entries (only MLP-FFN variants; ViT-g uses SwiGLU).
DINOV2_PRESETS: dict[str, dict[str, Any]] = {
    "dinov2_vits14": {"embed_dim": 384, "depth": 12, "num_heads": 6},
    "dinov2_vitb14": {"embed_dim": 768, "depth": 12, "num_heads": 12},
    "dinov2_vitl14": {"embed_dim": 1024, "depth": 24, "num_heads": 16},
}


class PatchEmbed(nn.Module):
    """``[B,3,H,W] -> [B, (H/p)*(W/p), D]`` by a strided convolution ``proj``."""

    def __init__(self, patch_size: int, in_chans: int, embed_dim: int) -> None:
        super().__init__()
        self.patch_size = patch_size
        self.proj = nn.Conv2d(in_chans, embed_dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(x).flatten(2).transpose(1, 2)


class Attention(nn.Module):
    """Multi-head self-attention with fused ``qkv`` and output ``proj``."""

    def __init__(self, dim: int, num_heads: int, qkv_bias: bool = True) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.qkv = nn.Linear(dim, dim * 3, bias=qkv_bias)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, N, C = x.shape
        qkv = self.qkv(x).reshape(B, N, 3, self.num_heads, C // self.num_heads)
        q, k, v = (t.transpose(1, 2) for t in qkv.unbind(2))
        x = F.scaled_dot_product_attention(q, k, v)
        return self.proj(x.transpose(1, 2).reshape(B, N, C))


class Mlp(nn.Module):
    """``fc1 -> GELU -> fc2``."""

    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(x)))


class LayerScale(nn.Module):
    """Per-channel residual scale ``gamma`` (init 1.0 in the hub models)."""

    def __init__(self, dim: int, init_value: float) -> None:
        super().__init__()
        self.gamma = nn.Parameter(torch.full((dim,), float(init_value)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gamma


class Block(nn.Module):
    """Pre-norm transformer block with layer scale: ``x + ls(attn(norm(x)))``, then MLP alike."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float, init_values: float) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attn = Attention(dim, num_heads)
        self.ls1 = LayerScale(dim, init_values)
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))
        self.ls2 = LayerScale(dim, init_values)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.ls1(self.attn(self.norm1(x)))
        return x + self.ls2(self.mlp(self.norm2(x)))


class DinoVisionTransformer(nn.Module):
    """DINOv2 ViT with the hub state-dict layout.

    ``forward`` is not defined on purpose: callers use :meth:`forward_tokens`
    (what SALAD consumes) or :meth:`prepare_tokens` + ``blocks`` + ``norm``.
    """

    default_conf: dict[str, Any] = {
        "preset": "dinov2_vitb14",
        "img_size": 518,  # size the positional embeddings were trained at
        "patch_size": 14,
        "mlp_ratio": 4.0,
        "init_values": 1.0,
        "num_register_tokens": 0,
        "interpolate_offset": 0.1,
        "interpolate_antialias": False,
        # Explicit overrides of the preset (small random-weight test models).
        "embed_dim": None,
        "depth": None,
        "num_heads": None,
    }

    def __init__(self, **conf: Any) -> None:
        super().__init__()
        c = merge_conf(self.default_conf, conf, "DINOv2 conf")
        if c["preset"] not in DINOV2_PRESETS:
            raise DinoV2Error(f"DINOv2 preset {c['preset']!r} not supported; choose one of {sorted(DINOV2_PRESETS)}")
        for k, v in DINOV2_PRESETS[c["preset"]].items():
            if c[k] is None:
                c[k] = v
        self.conf = c
        D, p = c["embed_dim"], c["patch_size"]
        self.embed_dim = D
        self.patch_size = p
        self.num_register_tokens = c["num_register_tokens"]
        grid = c["img_size"] // p
        self.patch_embed = PatchEmbed(p, 3, D)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, D))
        self.pos_embed = nn.Parameter(torch.zeros(1, grid * grid + 1, D))
        self.register_tokens = (
            nn.Parameter(torch.zeros(1, self.num_register_tokens, D)) if self.num_register_tokens else None
        )
        self.blocks = nn.ModuleList(
            [Block(D, c["num_heads"], c["mlp_ratio"], c["init_values"]) for _ in range(c["depth"])]
        )
        self.norm = nn.LayerNorm(D, eps=1e-6)
        self.mask_token = nn.Parameter(torch.zeros(1, D))
        nn.init.trunc_normal_(self.pos_embed, std=0.02)
        nn.init.normal_(self.cls_token, std=1e-6)

    def interpolate_pos_encoding(self, n_tokens: int, H: int, W: int) -> torch.Tensor:
        """Positional embeddings ``[1, 1 + (H/p)*(W/p), D]`` for an ``H x W`` input."""
        N = self.pos_embed.shape[1] - 1
        if n_tokens - 1 == N and H == W:
            return self.pos_embed
        pos = self.pos_embed.float()
        M = int(math.sqrt(N))
        h0, w0 = H // self.patch_size, W // self.patch_size
        off = self.conf["interpolate_offset"]
        # Upstream passes a scale factor (with a historical +0.1) rather than a size;
        # the bicubic sample positions depend on it, so do the same for equal numbers.
        kwargs: dict[str, Any] = (
            {"scale_factor": ((h0 + off) / M, (w0 + off) / M)} if off else {"size": (h0, w0)}
        )
        patch = F.interpolate(
            pos[:, 1:].reshape(1, M, M, -1).permute(0, 3, 1, 2),
            mode="bicubic", antialias=self.conf["interpolate_antialias"], **kwargs)
        if patch.shape[-2:] != (h0, w0):
            raise DinoV2Error(f"positional embedding resampled to {tuple(patch.shape[-2:])}, need {(h0, w0)}")
        patch = patch.permute(0, 2, 3, 1).reshape(1, h0 * w0, -1)
        return torch.cat([pos[:, :1], patch], dim=1).to(self.pos_embed.dtype)

    def prepare_tokens(self, x: torch.Tensor) -> torch.Tensor:
        """``[B,3,H,W]`` (normalised) -> ``[B, 1 + R + h*w, D]``: CLS, registers, patches."""
        if x.ndim != 4 or x.shape[1] != 3:
            raise DinoV2Error(f"DINOv2 input: expected [B,3,H,W], got {tuple(x.shape)}")
        B, _, H, W = x.shape
        if H % self.patch_size or W % self.patch_size:
            raise DinoV2Error(f"DINOv2 input {H}x{W} is not a multiple of the patch size {self.patch_size}")
        t = self.patch_embed(x)
        t = torch.cat([self.cls_token.expand(B, -1, -1), t], dim=1)
        t = t + self.interpolate_pos_encoding(t.shape[1], H, W).to(t.dtype)
        if self.register_tokens is not None:
            t = torch.cat([t[:, :1], self.register_tokens.expand(B, -1, -1), t[:, 1:]], dim=1)
        return t

    def forward_tokens(self, x: torch.Tensor, norm: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """Run all blocks.

        Args:
            x: ``[B,3,H,W]`` ImageNet-normalised, ``H, W`` multiples of 14.
            norm: apply the final LayerNorm (SALAD's ``norm_layer=True``).

        Returns:
            ``patches [B,D,H/14,W/14]`` (feature map, row-major patch order) and
            ``cls [B,D]``.
        """
        B, _, H, W = x.shape
        t = self.prepare_tokens(x)
        for blk in self.blocks:
            t = blk(t)
        if norm:
            t = self.norm(t)
        cls = t[:, 0]
        patches = t[:, 1 + self.num_register_tokens:]
        patches = patches.reshape(B, H // self.patch_size, W // self.patch_size, -1).permute(0, 3, 1, 2)
        return patches, cls
