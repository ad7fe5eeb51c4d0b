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


def _feats(desc: np.ndarray, key: bytes):
    from cerpe.backbones.xfeat import XFeatFeatures

    n = len(desc)
    return XFeatFeatures(keypoints=np.zeros((n, 2), np.float32), descriptors=desc, scores=np.ones(n, np.float32),
                         dense=np.zeros((64, 1, 1), np.float32), reliability=np.zeros((1, 1), np.float32),
                         image_hw=(8, 8), fingerprint=key)


def test_pair_matcher_answers_the_same_in_either_order_and_from_its_cache():
    """A hit equals a recomputation: the pair is matched once, in content-key order, and the
    other order gets the same pairs swapped and sorted; a fresh matcher answers the same."""
    from cerpe.backbones.offline import PairMatcher

    rng = np.random.default_rng(2)
    d0 = _unit(rng.normal(size=(300, 64)))
    d1 = _unit(d0[rng.permutation(300)] + 0.05 * rng.normal(size=(300, 64)))
    fa, fb = _feats(d0, b"\x02" * 16), _feats(d1, b"\x01" * 16)  # b sorts first: a->b is the flipped order
    warm = PairMatcher(0.82, 0.95, 8)
    m_ab, m_ba = warm(fa, fb), warm(fb, fa)
    assert warm.n_computed == 1 and warm.n_cached == 1
    assert np.all(np.diff(m_ab[:, 0]) > 0) and np.all(np.diff(m_ba[:, 0]) > 0)
    assert sorted(m_ab[:, ::-1].tolist()) == m_ba.tolist()
    for order in ((fa, fb), (fb, fa)):
        assert np.array_equal(PairMatcher(0.82, 0.95, 8)(*order), warm(*order))
    # other pixels under the same view: another content key, another entry
    fc = _feats(_unit(rng.normal(size=(300, 64))), b"\x03" * 16)
    assert len(warm(fa, fc)) < 10 and warm.n_computed == 2
