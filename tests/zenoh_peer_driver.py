"""A small robot stand-in over ZenohLink: real cerpe frames, step by step, no models.

Used by the link-level subprocess test (tests/test_online_zenoh_link.py), which checks
ZenohLink across processes without loading any model (the real robot processes, ``cerpe
online``, are tested in tests/test_online_cli.py and tests/test_online_zenoh_netns.py).
Per step it does what a robot's phases do on the wire:
broadcast its DescriptorMessage, gather the peers', request every peer's image
(ImageRequest -> ImageReply through the owner's queryable), broadcast its
PoseMessage, gather the peers'. Every frame's content is a function of
(robot, step), so each receiver checks what it got against what the sender must
have sent. Writes one JSON report (``--out``)::

    {"robot", "steps", "expected", "received", "bad_content", "degradations": {name: n},
     "bytes_per_step": {kind: bytes}, "step_s": [..], "stats": {...}, "missing_at_start": [..]}

Run: ``python tests/zenoh_peer_driver.py --robot r0 --roster r0,r1 --listen tcp/127.0.0.1:7447 ...``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cerpe.geometry import random_se3  # noqa: E402
from cerpe.messages import DescriptorMessage, ImageReply, ImageRequest, PoseMessage, decode  # noqa: E402
from cerpe.online.zenoh_link import ZenohLink  # noqa: E402

DIM = 64
HELD_STEPS = 2  # an image is held for this many steps (older requests: "not held")


def descriptor(index: int, step: int) -> np.ndarray:
    return np.random.default_rng([index, step, 1]).standard_normal(DIM).astype(np.float32)


def pose(index: int, step: int) -> np.ndarray:
    return random_se3(np.random.default_rng([index, step, 2]), max_translation=2.0)


def image(index: int, step: int) -> np.ndarray:
    return np.random.default_rng([index, step, 3]).integers(0, 255, (48, 64, 3), dtype=np.uint8)


def run(args: argparse.Namespace) -> dict:
    roster = args.roster.split(",")
    conf = {"team": args.team, "listen": args.listen, "connect": args.connect,
            "multicast_scouting": args.multicast}
    link = ZenohLink(args.robot, roster, conf)
    me = roster.index(args.robot)
    peers = [r for r in roster if r != args.robot]
    state = {"step": 0}
    sent: Counter[str] = Counter()  # frame bytes this robot sent, per kind

    def handler(peer: str, req: ImageRequest) -> bytes | None:
        if not (state["step"] - HELD_STEPS < req.step <= state["step"]):
            return None
        reply = ImageReply.from_image(me, req.step, image(me, req.step), (50.0, 50.0, 32.0, 24.0)).encode()
        sent["reply"] += len(reply)
        return reply

    link.serve(handler)
    missing = link.wait_peers(peers, args.connect_timeout)
    degr: Counter[str] = Counter()
    count: Counter[str] = Counter()  # expected, received, bad_content
    step_s = []

    def tally(inbox, right) -> None:
        degr.update(inbox.degradations)
        for p in peers:
            m = inbox.message(p)
            count["expected"] += 1
            count["received"] += m is not None
            count["bad_content"] += m is not None and not right(p, m)

    for t in range(args.steps):
        t0 = time.perf_counter()
        state["step"] = t
        link.begin(t)
        sent["descriptor"] += link.broadcast("descriptor", DescriptorMessage(me, t, descriptor(me, t)).encode())
        tally(link.gather(t, "descriptor", peers, args.deadline),
              lambda p, m: decode(DescriptorMessage(roster.index(p), t, descriptor(roster.index(p), t)).encode())
              .descriptor.tobytes() == m.descriptor.tobytes())
        replies = link.request(t, {p: ImageRequest(me, t, roster.index(p)).encode() for p in peers}, args.deadline)
        sent["request"] += sum(replies.sent.values())
        tally(replies, lambda p, m: m.step == t and m.image_rgb().shape == (48, 64, 3))
        sent["pose"] += link.broadcast("pose", PoseMessage(me, t, pose(me, t)).encode())
        tally(link.gather(t, "pose", peers, args.deadline),
              lambda p, m: np.allclose(m.T_odom_cam, pose(roster.index(p), t), atol=1e-9))
        step_s.append(time.perf_counter() - t0)
        link.poll(args.step_sleep)  # idle between steps, still answering requests
    degr.update(link.take_degradations())
    link.close(linger_s=args.linger)
    stats = {k: v for k, v in link.stats.items()}
    return {"robot": args.robot, "steps": args.steps,
            **{k: int(count[k]) for k in ("expected", "received", "bad_content")},
            "degradations": dict(degr), "bytes_per_step": {k: v / args.steps for k, v in sent.items()},
            "step_s": step_s, "stats": stats, "missing_at_start": missing}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robot", required=True)
    p.add_argument("--roster", required=True, help="robot ids in wire-index order, comma separated")
    p.add_argument("--team", default="drv")
    p.add_argument("--listen", action="append", default=[])
    p.add_argument("--connect", action="append", default=[])
    p.add_argument("--multicast", action="store_true", help="multicast scouting (default off)")
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--deadline", type=float, default=2.0)
    p.add_argument("--connect-timeout", type=float, default=10.0)
    p.add_argument("--step-sleep", type=float, default=0.0, help="idle seconds between steps")
    p.add_argument("--linger", type=float, default=3.0)
    p.add_argument("--out", required=True, type=Path)
    args = p.parse_args(argv)
    report = run(args)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(report))
    tmp.replace(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
