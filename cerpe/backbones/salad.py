"""SALAD aggregation (Izquierdo & Civera, CVPR 2024) in plain PyTorch.

Two layers, as in LightGlue's style:

* a functional core with no parameters -- :func:`log_otp_solver`,
  :func:`log_transport_plan`, :func:`salad_aggregate` -- shared by the paper's
  DINOv2 descriptor (:mod:`cerpe.backbones.salad_dinov2`) and by the
  training-free descriptor of the offline profile;
* :class:`SALADHead`, the learned head with upstream's submodule and parameter
  names (``score``, ``cluster_features``, ``token_features``, ``dust_bin``), so
  the official checkpoint's ``aggregator.*`` tensors load one-to-one.

Shapes (``B`` batch, ``n`` local features, ``m`` clusters, ``l`` reduced feature
dim, ``g`` token dim):

* ``features [B,l,n]`` reduced local features, ``scores [B,m,n]`` feature-to-
  cluster scores, ``token [B,g]`` global token -> descriptor ``[B, g + m*l]``.

Optimal transport (the paper's Sec. 3.2 of SALAD): the score matrix gets one
extra "dustbin" row filled with the scalar ``dust_bin``. The source marginal is
``1/(n+m)`` per cluster and ``(n-m)/(n+m)`` for the dustbin, the target marginal
``1/(n+m)`` per feature (both carry the same mass ``n/(n+m)``). Three log-space Sinkhorn
iterations follow. The plan is then multiplied by ``n+m`` so that each feature distributes
a mass of one, the dustbin row is dropped, and per cluster a weighted sum of features
is taken.

Descriptor layout (identical to upstream, element order matters for checkpoints
and for anyone comparing descriptors): ``[ normalize(token) (g values),
normalize_per_cluster(agg) flattened from [l, m] row-major (index = i_l*m + i_m) ]``,
then the whole vector is L2-normalised.
"""
from __future__ import annotations

import math
from typing import Any

import torch
import torch.nn as nn
import torch.nn.functional as F

from ..config import merge_conf
from ..errors import CerpeError


class SaladError(CerpeError, ValueError):
    """Malformed input to the SALAD aggregation (shapes, too few features)."""


def log_otp_solver(
    log_a: torch.Tensor, log_b: torch.Tensor, M: torch.Tensor, num_iters: int = 3, reg: float = 1.0
) -> torch.Tensor:
    """Entropic optimal transport by Sinkhorn scaling in log space.

    Args:
        log_a: ``[B,M]`` log source marginal (rows of ``M``).
        log_b: ``[B,N]`` log target marginal (columns).
        M: ``[B,M,N]`` scores (a *gain*, not a cost: higher = more mass).
        num_iters: alternating row/column updates; the column marginal is exact
            after every iteration (the column update is last), the row marginal
            only in the limit.
        reg: entropic temperature; scores are divided by it.

    Returns:
        ``[B,M,N]`` log transport plan ``log P`` with ``P.sum(-1) ~ a`` and
        ``P.sum(-2) = b``.
    """
    M = M / reg
    u = torch.zeros_like(log_a)
    v = torch.zeros_like(log_b)
    for _ in range(num_iters):
        # No squeeze (upstream squeezes, which only works by broadcasting luck at B=1).
        u = log_a - torch.logsumexp(M + v.unsqueeze(1), dim=2)
        v = log_b - torch.logsumexp(M + u.unsqueeze(2), dim=1)
    return M + u.unsqueeze(2) + v.unsqueeze(1)


def salad_marginals(m: int, n: int, batch: int = 1, dtype: torch.dtype = torch.float32,
                    device: torch.device | str | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The SALAD marginals in log space.

    Returns:
        ``log_a [batch, m+1]``: ``log 1/(n+m)`` per cluster, ``log (n-m)/(n+m)``
        for the dustbin (last row); ``log_b [batch, n]``: ``log 1/(n+m)``.

    Raises:
        SaladError: when ``n <= m`` (the dustbin would get no or negative mass).
    """
    if n <= m:
        raise SaladError(f"SALAD needs more local features than clusters: n={n} <= m={m}")
    norm = -math.log(n + m)
    log_a = torch.full((batch, m + 1), norm, dtype=dtype, device=device)
    log_a[:, -1] = norm + math.log(n - m)
    log_b = torch.full((batch, n), norm, dtype=dtype, device=device)
    return log_a, log_b


def log_transport_plan(scores: torch.Tensor, dust_bin: torch.Tensor | float, iters: int = 3) -> torch.Tensor:
    """Log transport plan of features onto clusters plus a dustbin.

    Args:
        scores: ``[B,m,n]`` cluster scores of each local feature.
        dust_bin: scalar score of the dustbin row (learned; upstream init 1.0).
        iters: Sinkhorn iterations (3 in SALAD).

    Returns:
        ``[B,m+1,n]`` log plan whose marginals are :func:`salad_marginals` (it
        has total mass ``n/(n+m)``; multiply by ``n+m`` to give each feature unit mass).
    """
    if scores.ndim != 3:
        raise SaladError(f"scores: expected [B,m,n], got {tuple(scores.shape)}")
    B, m, n = scores.shape
    dust = torch.as_tensor(dust_bin, dtype=scores.dtype, device=scores.device)
    S_aug = torch.cat([scores, dust.reshape(1, 1, 1).expand(B, 1, n)], dim=1)
    log_a, log_b = salad_marginals(m, n, B, scores.dtype, scores.device)
    return log_otp_solver(log_a, log_b, S_aug, num_iters=iters)


def salad_aggregate(
    features: torch.Tensor,
    scores: torch.Tensor,
    token: torch.Tensor,
    dust_bin: torch.Tensor | float,
    iters: int = 3,
) -> torch.Tensor:
    """SALAD global descriptor from reduced features, scores and a token.

    Order of operations (upstream's exactly):

    1. ``P = exp(log_transport_plan(scores)) * (n+m)`` -> ``[B,m+1,n]``;
       drop the dustbin row -> ``[B,m,n]``.
    2. ``V[b,:,k] = sum_i P[b,k,i] * features[b,:,i]`` -> ``[B,l,m]``.
    3. L2-normalise each cluster column ``V[b,:,k]`` (over ``l``); flatten
       row-major -> ``[B,l*m]``.
    4. prepend ``normalize(token)`` -> ``[B, g + l*m]``; L2-normalise all.

    Args:
        features: ``[B,l,n]``; scores: ``[B,m,n]``; token: ``[B,g]`` (``g`` may be 0).
        dust_bin: dustbin score; iters: Sinkhorn iterations.

    Returns:
        ``[B, m*l + g]`` unit-norm descriptors.
    """
    if features.ndim != 3 or scores.ndim != 3 or token.ndim != 2:
        raise SaladError(
            f"salad_aggregate: expected features [B,l,n], scores [B,m,n], token [B,g]; got "
            f"{tuple(features.shape)}, {tuple(scores.shape)}, {tuple(token.shape)}")
    B, _, n = features.shape
    if scores.shape[0] != B or scores.shape[2] != n or token.shape[0] != B:
        raise SaladError(
            f"salad_aggregate: batch/feature counts disagree: features {tuple(features.shape)}, "
            f"scores {tuple(scores.shape)}, token {tuple(token.shape)}")
    m = scores.shape[1]
    P = torch.exp(log_transport_plan(scores, dust_bin, iters) + math.log(n + m))[:, :m, :]
    agg = torch.einsum("bln,bmn->blm", features, P)
    agg = F.normalize(agg, p=2, dim=1).flatten(1)
    if token.shape[1] > 0:
        out = torch.cat([F.normalize(token, p=2, dim=-1), agg], dim=-1)
    else:
        out = agg
    return F.normalize(out, p=2, dim=-1)


class SALADHead(nn.Module):
    """Learned SALAD head with upstream's module layout (``models/aggregators/salad.py``).

    Parameter names (what ``aggregator.*`` in the official checkpoint holds):
    ``token_features.{0,2}.{weight,bias}`` (Linear C->512->g),
    ``cluster_features.{0,3}.{weight,bias}`` (1x1 Conv C->512->l, dropout at index 1),
    ``score.{0,3}.{weight,bias}`` (1x1 Conv C->512->m), ``dust_bin`` (scalar).

    Official sizes (DINOv2 ViT-B/14): C=768, m=64, l=128, g=256 -> 8448 dims.
    """

    default_conf: dict[str, Any] = {
        "num_channels": 768,
        "num_clusters": 64,
        "cluster_dim": 128,
        "token_dim": 256,
        "hidden_dim": 512,
        "dropout": 0.3,
        "sinkhorn_iters": 3,
    }

    def __init__(self, **conf: Any) -> None:
        super().__init__()
        self.conf = merge_conf(self.default_conf, conf, "SALADHead conf")
        c = self.conf
        C, h = c["num_channels"], c["hidden_dim"]
        drop: nn.Module = nn.Dropout(c["dropout"]) if c["dropout"] > 0 else nn.Identity()
        self.token_features = nn.Sequential(nn.Linear(C, h), nn.ReLU(), nn.Linear(h, c["token_dim"]))
        self.cluster_features = nn.Sequential(
            nn.Conv2d(C, h, 1), drop, nn.ReLU(), nn.Conv2d(h, c["cluster_dim"], 1))
        self.score = nn.Sequential(nn.Conv2d(C, h, 1), drop, nn.ReLU(), nn.Conv2d(h, c["num_clusters"], 1))
        self.dust_bin = nn.Parameter(torch.tensor(1.0))

    @property
    def dim(self) -> int:
        """Descriptor length ``m*l + g``."""
        c = self.conf
        return c["num_clusters"] * c["cluster_dim"] + c["token_dim"]

    def forward(self, features: torch.Tensor, token: torch.Tensor) -> torch.Tensor:
        """Aggregate a patch-feature map and its class token.

        Args:
            features: ``[B,C,h,w]`` patch tokens as a feature map (``h*w > m``).
            token: ``[B,C]`` class token.

        Returns:
            ``[B, m*l+g]`` L2-normalised descriptors.
        """
        C = self.conf["num_channels"]
        if features.ndim != 4 or features.shape[1] != C or token.shape != (features.shape[0], C):
            raise SaladError(
                f"SALADHead: expected features [B,{C},h,w] and token [B,{C}], got "
                f"{tuple(features.shape)} and {tuple(token.shape)}")
        f = self.cluster_features(features).flatten(2)
        p = self.score(features).flatten(2)
        t = self.token_features(token)
        return salad_aggregate(f, p, t, self.dust_bin, self.conf["sinkhorn_iters"])
