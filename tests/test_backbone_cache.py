"""The plug-ins' one LRU cache and their content key."""
from __future__ import annotations

import numpy as np

from cerpe.backbones.cache import LRUCache, content_key


def test_lru_forgets_the_least_recently_used():
    c: LRUCache[int] = LRUCache(2)
    c.put("a", 1)
    c.put("b", 2)
    assert c.get("a") == 1  # "b" is now the oldest
    c.put("c", 3)
    assert "b" not in c and c.get("a") == 1 and c.get("c") == 3 and len(c) == 2
    assert c.get("b") is None and (c.hits, c.misses) == (3, 1)
    c.clear()
    assert len(c) == 0
    none: LRUCache[int] = LRUCache(0)
    none.put("a", 1)
    assert none.get("a") is None


def test_content_key_tells_apart_values_shapes_and_dtypes():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    k = content_key(img)
    assert isinstance(k, bytes) and len(k) == 16
    assert content_key(img.copy()) == k
    assert content_key(np.asfortranarray(img)) == k  # memory layout does not matter
    other = img.copy()
    other[10, 20, 1] ^= 1
    assert content_key(other) != k
    assert content_key(img.reshape(64, 48, 3)) != k  # same bytes, another shape
    assert content_key(img.astype(np.int8)) != k  # same bytes, another dtype
    assert content_key(np.zeros((0, 3))) != content_key(np.zeros((3, 0)))


def test_reserve_grows_a_cache_and_never_shrinks_it():
    c: LRUCache[int] = LRUCache(2)
    c.reserve(4)
    for k in range(5):
        c.put(k, k)
    assert len(c) == 4 and 0 not in c
    c.reserve(1)
    assert c.maxsize == 4


def test_a_team_sizes_the_shared_backbone_caches_for_its_robots():
    """Eight robots in one process share one backbone: its caches and the encoder's hold each robot's
    working set (otherwise the team re-encodes what two robots find cached)."""
    from cerpe.algorithm import Team
    from cerpe.backbones.build import build_plugins

    plugins = build_plugins()
    b = plugins.backbone
    before = (b.matcher.cache.maxsize, b.greys.maxsize, b.encoder._cache.maxsize)
    Team([f"r{k}" for k in range(8)], plugins.descriptor, b, plugins.depth)
    after = (b.matcher.cache.maxsize, b.greys.maxsize, b.encoder._cache.maxsize)
    assert all(a >= 8 * per for a, per in zip(after, (128, 24, 32)))
    assert all(a >= x for a, x in zip(after, before))
