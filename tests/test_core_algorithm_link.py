"""The link layer under the step engine: the mailbox both links share, and the in-process team's determinism."""
from __future__ import annotations

import numpy as np

from cerpe.algorithm import AlgorithmConfig, Link, Mailbox, Team
from cerpe.algorithm.channel_link import ChannelHub
from cerpe.messages import DescriptorMessage, ImageRequest, PoseMessage
from cerpe.online.zenoh_link import ZenohLink
from cerpe.transport import Channel
from gt_backbone import GTBackbone, OverlapDescriptor, SensorDepthDouble, make_world


def _desc(sender: int, step: int) -> DescriptorMessage:
    return DescriptorMessage(sender, step, np.ones(4, np.float32))


def test_mailbox_files_by_step_and_counts_what_it_drops():
    answered = []

    def handler(peer, req):
        answered.append((peer, req.step))
        return b"reply" if req.step == box.step else None

    box = Mailbox("a", ["a", "b", "c"], max_ahead_steps=2)
    box.handler = handler
    box.begin(3)
    assert box.file("b", _desc(1, 3), 30) == []
    box.file("b", _desc(1, 3), 30)                        # duplicate
    box.file("c", _desc(1, 3), 30)                        # index 1 is b, not c
    box.file("c", _desc(2, 2), 30)                        # a step already left
    box.file("c", _desc(2, 9), 30)                        # too far ahead
    box.file("c", PoseMessage(2, 4, np.eye(4)), 70)       # next step: kept for later
    assert box.file("b", ImageRequest(1, 2, 0), 16) == []  # stale request: handler counts it, no reply
    box.file("c", ImageRequest(2, 3, 0), 16)
    assert box.answer() == [("c", b"reply")] and box.answer() == []  # answered once
    assert answered == [("b", 2), ("c", 3)]
    inbox = box.inbox(3, "descriptor", ["b", "c"])
    assert list(inbox.messages) == ["b"] and inbox.messages["b"].nbytes == 30
    assert inbox.degradations == ["msg:unknown-sender"]
    assert box.inbox(3, "descriptor", ["b"]).degradations == []  # handed over once
    assert (box.stats["duplicate"], box.stats["late"], box.stats["too_far_ahead"]) == (1, 1, 1)
    box.begin(4)
    assert list(box.inbox(4, "pose", ["c"]).messages) == ["c"]
    assert box.have(3, "descriptor") == {}  # earlier steps dropped


def test_both_links_satisfy_the_protocol():
    hub = ChannelHub(Channel(), ["a", "b"])
    assert isinstance(hub.link("a"), Link)
    link = ZenohLink("a", ["a", "b"], {"multicast_scouting": False, "listen": ["tcp/127.0.0.1:0"]})
    try:
        assert isinstance(link, Link)
    finally:
        link.close(0.0)


def test_lossy_team_is_deterministic():
    world = make_world(3, 20, seed=6, windows={(0, 1): [(2, 9)], (0, 2): [(5, 12)], (1, 2): [(8, 16)]})

    def run():
        team = Team(world.robot_ids, OverlapDescriptor(world), GTBackbone(world, seed=1), SensorDepthDouble(),
                    AlgorithmConfig().override({"scale.min_pixels": 20}), Channel(p_drop=0.15, p_garble=0.1, seed=4))
        return [([(p.ego, p.other, p.source, p.reason, repr(p.gate_score), p.bytes_pair,
                   None if p.T_cj_ci is None else p.T_cj_ci.tobytes()) for p in res.pairs],
                 [(r.T_odom_cam.tobytes(), r.degradations, r.bytes_sent, r.keyframe) for r in res.robots])
                for res in team.run_encounter(world.to_encounter())]

    a, b = run(), run()
    assert a == b
    assert any(d == "msg:lost" for _, robots in a for r in robots for d in r[1])
    assert any(p[5] > 16 for pairs, _ in a for p in pairs)  # request sent + reply received
