"""The keyframe rule against a hand-computed sequence; eviction; bad input."""
from __future__ import annotations

import numpy as np
import pytest

from cerpe.algorithm.config import PAPER_THRESHOLDS
from cerpe.knobs import KnobError
from cerpe.memory import Keyframe, KeyframeMemory, KeyframeMemoryError, MemoryConfig, cosine, should_insert

CONF = MemoryConfig(tau_m=0.9, tau_k=0.2)  # paper: tau_m 0.9, tau_k 0.2, L 5; delta_k 3


def test_defaults_are_the_papers():
    # thresholds None: the descriptor's calibration, else the paper's (resolved by the algorithm's config)
    default = MemoryConfig()
    assert (default.tau_m, default.tau_k, default.capacity, default.delta_k) == (None, None, 5, 3)
    assert (PAPER_THRESHOLDS["tau_m"], PAPER_THRESHOLDS["tau_k"]) == (0.9, 0.2)
    assert KeyframeMemory().conf == CONF
    with pytest.raises(KeyframeMemoryError, match="resolved"):
        KeyframeMemory(MemoryConfig())


@pytest.mark.parametrize("c, delta, expected", [
    (None, None, (True, "empty")),
    (0.95, 10, (False, "skip")),            # small change, however long ago
    (0.9, 10, (False, "skip")),             # c == tau_m is not "< tau_m"
    (0.85, 3, (False, "skip")),             # moderate change but gap == delta_k is not "> delta_k"
    (0.85, 4, (True, "moderate-change")),
    (0.2, 1, (False, "skip")),              # c == tau_k is not a large change, gap too small
    (0.2, 4, (True, "moderate-change")),
    (0.19, 0, (True, "large-change")),      # large change: no gap needed
    (-0.5, 100, (True, "large-change")),    # both hold: reported as the large-change branch
])
def test_should_insert_branches(c, delta, expected):
    assert should_insert(c, delta, CONF) == expected


def _unit(theta: float) -> np.ndarray:
    return np.array([np.cos(theta), np.sin(theta), 0.0], np.float32)


def _kf(step: int, theta: float) -> Keyframe:
    return Keyframe(step=step, key=("r0", step), descriptor=_unit(theta), image=np.zeros((2, 3, 3), np.uint8),
                    intrinsics=None, T_odom_cam=np.eye(4))


def test_memory_follows_hand_computed_sequence():
    """Descriptors are unit vectors at angle theta, so c = cos(theta - theta_newest_kf).

    step theta  c vs newest kf         delta  decision
    0    0.0    (empty)                  -    insert (empty)
    1    0.3    cos .3  = .955           1    skip
    2    0.6    cos .6  = .825           2    skip (gap)
    3    0.6    .825                     3    skip (gap == delta_k)
    4    0.6    .825                     4    insert (moderate)        kf theta .6
    5    2.1    cos 1.5 = .071           1    insert (large)           kf theta 2.1
    6    2.3    cos .2  = .980           1    skip
    10   2.6    cos .5  = .878           5    insert (moderate)        kf theta 2.6
    11   4.0    cos 1.4 = .170           1    insert (large)           kf theta 4.0
    12   5.45   cos 1.45 = .121          1    insert (large) -> 6 > L: evict step 0
    13   5.5    cos .05 = .999           1    skip
    """
    mem = KeyframeMemory(CONF)
    seq = [(0, 0.0, True, "empty"), (1, 0.3, False, "skip"), (2, 0.6, False, "skip"), (3, 0.6, False, "skip"),
           (4, 0.6, True, "moderate-change"), (5, 2.1, True, "large-change"), (6, 2.3, False, "skip"),
           (10, 2.6, True, "moderate-change"), (11, 4.0, True, "large-change"),
           (12, 5.45, True, "large-change"), (13, 5.5, False, "skip")]
    evicted = []
    for step, theta, want, branch in seq:
        insert, got_branch, c, delta = mem.decide(_unit(theta), step)
        assert (insert, got_branch) == (want, branch), f"step {step}: c={c:.3f} delta={delta}"
        if insert:
            out = mem.insert(_kf(step, theta))
            if out is not None:
                evicted.append(out.step)
    assert [kf.step for kf in mem] == [4, 5, 10, 11, 12]
    assert [kf.step for kf in mem.newest_first()] == [12, 11, 10, 5, 4]
    assert evicted == [0]
    assert mem.newest().step == 12


def test_capacity_one_keeps_only_newest():
    mem = KeyframeMemory(MemoryConfig(tau_m=0.9, tau_k=0.2, capacity=1))
    for s in range(4):
        mem.insert(_kf(s, s * 2.0))
    assert [kf.step for kf in mem] == [3]


def test_cosine_of_zero_vector_is_nan():
    assert np.isnan(cosine(np.zeros(3), np.ones(3)))
    assert cosine(np.ones(3), 2 * np.ones(3)) == pytest.approx(1.0)


@pytest.mark.parametrize("kwargs, field", [
    (dict(tau_m=1.5), "tau_m"), (dict(tau_k=float("nan")), "tau_k"), (dict(tau_m=0.9, tau_k=0.95), "tau_k"),
    (dict(delta_k=-1), "delta_k"), (dict(capacity=0), "capacity"), (dict(delta_k=2.5), "delta_k"),
])
def test_bad_config_names_field(kwargs, field):
    with pytest.raises(KnobError, match=field):
        MemoryConfig(**kwargs)


def test_bad_queries_and_keyframes():
    mem = KeyframeMemory()
    with pytest.raises(KeyframeMemoryError, match="empty"):
        mem.newest()
    with pytest.raises(KeyframeMemoryError, match="finite"):
        should_insert(float("nan"), 3, CONF)
    with pytest.raises(KeyframeMemoryError, match="delta"):
        should_insert(0.5, None, CONF)
    with pytest.raises(KeyframeMemoryError, match="descriptor"):
        _bad = Keyframe(0, ("r0", 0), np.zeros(3), np.zeros((2, 2, 3), np.uint8), None, np.eye(4))
    with pytest.raises(KeyframeMemoryError, match="image"):
        Keyframe(0, ("r0", 0), np.ones(3), np.zeros((0, 2, 3), np.uint8), None, np.eye(4))
    bad_T = np.eye(4)
    bad_T[0, 3] = np.nan
    with pytest.raises(KeyframeMemoryError, match="T_odom_cam"):
        Keyframe(0, ("r0", 0), np.ones(3), np.zeros((2, 2, 3), np.uint8), None, bad_T)
    with pytest.raises(KeyframeMemoryError, match="depth_ref_m"):
        Keyframe(0, ("r0", 0), np.ones(3), np.zeros((2, 2, 3), np.uint8), None, np.eye(4), np.zeros(5))
    mem.insert(_kf(5, 0.0))
    with pytest.raises(KeyframeMemoryError, match="not after"):
        mem.insert(_kf(5, 1.0))
    with pytest.raises(KeyframeMemoryError, match="zero norm"):
        mem.decide(np.zeros(3), 6)
    with pytest.raises(KeyframeMemoryError, match="lengths differ"):
        mem.decide(np.ones(4), 6)
