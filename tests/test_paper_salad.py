"""SALAD aggregation: transport marginals, output layout, upstream parameter names."""
from __future__ import annotations

import math

import pytest
import torch

from cerpe.backbones.salad import (
    SALADHead,
    SaladError,
    log_transport_plan,
    salad_aggregate,
    salad_marginals,
)

# Parameter names of serizba/salad models/aggregators/salad.py (SALAD(num_channels=768)),
# written out here so a rename on our side cannot go unnoticed.
UPSTREAM_AGGREGATOR_SHAPES = {
    "dust_bin": (),
    "token_features.0.weight": (512, 768),
    "token_features.0.bias": (512,),
    "token_features.2.weight": (256, 512),
    "token_features.2.bias": (256,),
    "cluster_features.0.weight": (512, 768, 1, 1),
    "cluster_features.0.bias": (512,),
    "cluster_features.3.weight": (128, 512, 1, 1),
    "cluster_features.3.bias": (128,),
    "score.0.weight": (512, 768, 1, 1),
    "score.0.bias": (512,),
    "score.3.weight": (64, 512, 1, 1),
    "score.3.bias": (64,),
}


def test_marginals_values() -> None:
    log_a, log_b = salad_marginals(m=4, n=10, batch=2)
    a, b = log_a.exp(), log_b.exp()
    assert torch.allclose(a[:, :4], torch.full((2, 4), 1 / 14))
    assert torch.allclose(a[:, 4], torch.full((2,), 6 / 14))
    assert torch.allclose(b, torch.full((2, 10), 1 / 14))
    # Both marginals carry the same total mass n/(n+m) (not 1): the plan is balanced.
    assert torch.allclose(a.sum(-1), torch.full((2,), 10 / 14))
    assert torch.allclose(b.sum(-1), torch.full((2,), 10 / 14))


def test_transport_plan_marginals() -> None:
    torch.manual_seed(0)
    B, m, n = 2, 5, 40
    scores = torch.randn(B, m, n) * 3
    # Three iterations (SALAD): column marginal exact (last update), rows approximate.
    P3 = log_transport_plan(scores, 1.0, iters=3).exp()
    assert torch.allclose(P3.sum(1), torch.full((B, n), 1 / (n + m)), atol=1e-6)
    # Many iterations: both marginals as specified.
    P = log_transport_plan(scores, 1.0, iters=200).exp()
    assert torch.allclose(P.sum(1), torch.full((B, n), 1 / (n + m)), atol=1e-6)
    rows = P.sum(2)
    assert torch.allclose(rows[:, :m], torch.full((B, m), 1 / (n + m)), atol=1e-5)
    assert torch.allclose(rows[:, m], torch.full((B,), (n - m) / (n + m)), atol=1e-5)


def test_aggregate_known_answer_one_hot_assignment() -> None:
    # Scores strongly favouring cluster k for feature group k: each cluster's vector
    # is the normalised mean of its group's features.
    m, l, n = 2, 3, 8
    feats = torch.zeros(1, l, n)
    feats[0, 0, :4] = 1.0  # cluster 0 features point along axis 0
    feats[0, 1, 4:] = 2.0  # cluster 1 features along axis 1
    scores = torch.full((1, m, n), -50.0)
    scores[0, 0, :4] = 50.0
    scores[0, 1, 4:] = 50.0
    token = torch.tensor([[3.0, 4.0]])
    d = salad_aggregate(feats, scores, token, dust_bin=-50.0, iters=3)
    assert d.shape == (1, 2 + m * l)
    expected = torch.tensor([0.6, 0.8, 1, 0, 0, 1, 0, 0]) / math.sqrt(3.0)
    # layout: token, then [l, m] row-major: (l0,m0)=1 (l0,m1)=0 (l1,m0)=0 (l1,m1)=1 ...
    assert torch.allclose(d[0], expected, atol=1e-4)


def test_head_official_sizes_unit_norm() -> None:
    torch.manual_seed(1)
    head = SALADHead().eval()
    assert head.dim == 8448
    with torch.no_grad():
        d = head(torch.randn(2, 768, 23, 23), torch.randn(2, 768))
    assert d.shape == (2, 8448)
    assert torch.allclose(d.norm(dim=-1), torch.ones(2), atol=1e-5)
    assert torch.isfinite(d).all()


def test_head_parameter_names_match_upstream() -> None:
    sd = SALADHead().state_dict()
    assert {k: tuple(v.shape) for k, v in sd.items()} == UPSTREAM_AGGREGATOR_SHAPES
    assert float(sd["dust_bin"]) == 1.0


def test_batch_of_one_equals_batched() -> None:
    torch.manual_seed(2)
    head = SALADHead(num_channels=16, num_clusters=4, cluster_dim=8, token_dim=6, hidden_dim=12).eval()
    x, t = torch.randn(3, 16, 5, 5), torch.randn(3, 16)
    with torch.no_grad():
        full = head(x, t)
        single = torch.cat([head(x[i : i + 1], t[i : i + 1]) for i in range(3)])
    assert torch.allclose(full, single, atol=1e-6)


def test_errors() -> None:
    with pytest.raises(SaladError, match="n=3 <= m=4"):
        salad_aggregate(torch.randn(1, 2, 3), torch.randn(1, 4, 3), torch.randn(1, 2), 1.0)
    with pytest.raises(SaladError, match="batch"):
        salad_aggregate(torch.randn(2, 2, 9), torch.randn(1, 4, 9), torch.randn(2, 2), 1.0)
    from cerpe.config import ConfigError

    with pytest.raises(ConfigError, match="SALADHead conf: unknown option.*'clusters'; known: .*num_clusters"):
        SALADHead(clusters=3)
    with pytest.raises(SaladError, match="expected features"):
        SALADHead()(torch.randn(1, 10, 4, 4), torch.randn(1, 10))
