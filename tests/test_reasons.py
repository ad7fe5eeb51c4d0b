"""The reasons and degradations of the records are one closed vocabulary without numbers."""
from __future__ import annotations

import numpy as np
import pytest

from cerpe.reasons import (DEGRADATIONS, REASONS, SEPARATOR, VocabularyError, check_degradations, check_reason, join,
                           split)
from cerpe.records import PairRecord, RobotRecord
from gt_backbone import GTBackbone, OverlapDescriptor, SensorDepthDouble, make_world


def test_the_vocabulary_is_described_and_holds_no_numbers():
    for name, vocab in (("reason", REASONS), ("degradation", DEGRADATIONS)):
        for token, doc in vocab.items():
            assert doc.strip(), f"{name} {token!r} has no description"
            assert not any(c.isdigit() for c in token), f"{name} {token!r} carries a number"
            assert SEPARATOR not in token and token == token.strip()


def test_join_and_split_round_trip_and_refuse_unknown_tokens():
    assert join("", "no-anchor", "") == "no-anchor"
    assert join("gate-closed; stale-pose", "unverified") == "gate-closed; stale-pose; unverified"
    assert split(join("reply-missing", "unverified")) == ["reply-missing", "unverified"] and split("") == []
    for bad in ("direct-weak: 25 inliers < 40", "no-such-reason", "gate-closed; nope"):
        with pytest.raises(VocabularyError, match="not in cerpe.reasons.REASONS"):
            check_reason(bad)
    with pytest.raises(VocabularyError, match="scale:skipped-"):
        check_degradations(["scale:skipped-"])


def _pair(reason: str) -> PairRecord:
    return PairRecord(step=0, stamp_s=0.0, ego="a", other="b", gate_score=0.1, gate_open=False, source="none",
                      T_cj_ci=None, reason=reason)


def test_records_refuse_words_outside_the_vocabulary():
    assert _pair("gate-closed").reason == "gate-closed"
    with pytest.raises(VocabularyError):
        _pair("anchor-not-stored: pose message missing")
    with pytest.raises(VocabularyError):
        RobotRecord(step=0, stamp_s=0.0, robot="a", T_odom_cam=np.eye(4), scale=1.0, n_keyframes=0, keyframe=False,
                    degradations=["frame:blank", "frame:blurry"])


def test_a_run_uses_few_distinct_reasons_however_long():
    """Numbers are columns: a run's reasons are a handful of tokens, not one string per step."""
    from cerpe.algorithm import AlgorithmConfig, Team

    world = make_world(2, 60, seed=3)
    team = Team(world.robot_ids, OverlapDescriptor(world), GTBackbone(world, seed=1, trans_noise=0.05,
                                                                      rot_noise_rad=0.05),
                SensorDepthDouble(), AlgorithmConfig().override({"scale.min_pixels": 20}))
    reasons = {p.reason for res in team.run_encounter(world.to_encounter()) for p in res.pairs}
    tokens = {t for r in reasons for t in split(r)}
    assert tokens <= set(REASONS) and len(reasons) <= 12, reasons
