"""Mutual-nearest-neighbour matching of the offline backbone: known answers on synthetic descriptors."""
from __future__ import annotations

import numpy as np

from cerpe.backbones.offline import match_mnn


def _unit(a: np.ndarray) -> np.ndarray:
    return (a / np.linalg.norm(a, axis=1, keepdims=True)).astype(np.float32)


def test_permuted_noisy_copy_is_matched_back():
    rng = np.random.default_rng(0)
    d0 = _unit(rng.normal(size=(500, 64)))
    perm = rng.permutation(500)
    d1 = _unit(d0[perm] + 0.02 * rng.normal(size=(500, 64)))
    m = match_mnn(d0, d1)
    assert len(m) > 490
    assert np.all(perm[m[:, 1]] == m[:, 0])


def test_ratio_test_drops_ambiguous_duplicates_and_sizes_differ():
    rng = np.random.default_rng(1)
    d0 = _unit(rng.normal(size=(40, 64)))
    d1 = np.concatenate([d0[:30], d0[:5]])  # rows 0..4 of d0 appear twice in d1
    m = match_mnn(d0, d1, ratio=0.95)
    assert set(m[:, 0].tolist()) == set(range(5, 30))
    m_all = match_mnn(d0, d1, ratio=1.0)
    assert set(range(5, 30)) <= set(m_all[:, 0].tolist())
    assert match_mnn(d0[:0], d1).shape == (0, 2)
    assert match_mnn(d0[:1], d1[:1]).shape == (1, 2)
