"""ZenohLink on loopback: two and three peers in this process (and in subprocesses), explicit
tcp/127.0.0.1 endpoints on free ports, multicast scouting off (tests never depend on multicast).

Covers broadcast/gather of every kind, image request/reply through queryables, deadlines
(a missing or killed peer costs at most the deadline, then nothing), malformed payloads on our
keys, another team or protocol version, and sessions that cannot open.
"""
from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")

from cerpe.config import ConfigError  # noqa: E402
from cerpe.errors import CerpeError  # noqa: E402
from cerpe.geometry import random_se3  # noqa: E402
from cerpe.messages import DescriptorMessage, ImageReply, ImageRequest, PoseMessage, decode  # noqa: E402
from cerpe.online import zenoh_wire as w  # noqa: E402
from cerpe.online.zenoh_link import ZenohLink, ZenohLinkError  # noqa: E402

TESTS = Path(__file__).resolve().parent
DRIVER = TESTS / "zenoh_peer_driver.py"
SLACK_S = 3.0  # generous: the machine is shared; these bounds say "no hang", not "fast"


def free_ports(n: int) -> list[int]:
    socks = [socket.socket() for _ in range(n)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


class Team:
    """Links for ``up`` robots of ``roster``; robot k listens on its port and dials the earlier ones."""

    def __init__(self, roster, up=None, team="t", teams=None):
        self.roster = list(roster)
        up = list(up or roster)
        self.ports = dict(zip(self.roster, free_ports(len(self.roster))))
        self.links: dict[str, ZenohLink] = {}
        for k, r in enumerate(up):
            conf = {"team": (teams or {}).get(r, team), "multicast_scouting": False,
                    "listen": [endpoint(self.ports[r])], "connect": [endpoint(self.ports[q]) for q in up[:k]]}
            self.links[r] = ZenohLink(r, self.roster, conf)
        for link in self.links.values():  # every robot up before any waits for the others
            link.announce()
        for r, link in self.links.items():
            same = [q for q in self.links if q != r and self.links[q].team == link.team]
            assert link.wait_peers(same, 10.0) == [], f"{r} does not see {same}"

    def __getitem__(self, r):
        return self.links[r]

    def close(self):
        for link in self.links.values():
            link.close(linger_s=0.0)


@pytest.fixture
def team_of():
    made = []

    def make(*args, **kw):
        made.append(Team(*args, **kw))
        return made[-1]

    yield make
    for t in made:
        t.close()


def raw_session(port: int):
    c = zenoh.Config()
    for k, v in (("mode", "peer"), ("scouting/multicast/enabled", False), ("connect/endpoints", [endpoint(port)])):
        c.insert_json5(k, json.dumps(v))
    return zenoh.open(c)


def frames_of(k: int, t: int) -> dict[str, bytes]:
    rng = np.random.default_rng([k, t])
    return {"descriptor": DescriptorMessage(k, t, rng.standard_normal(32)).encode(),
            "pose": PoseMessage(k, t, random_se3(rng, 3.0)).encode()}


# --------------------------------------------------------------------------- broadcast / gather
@pytest.mark.parametrize("n", [2, 3])
def test_broadcast_gather_all_kinds(team_of, n):
    ids = [f"r{k}" for k in range(n)]
    team = team_of(ids)
    for t in range(4):
        for k, r in enumerate(ids):
            team[r].begin(t)
            for kind, frame in frames_of(k, t).items():
                assert team[r].broadcast(kind, frame) == len(frame)  # the frame's bytes, counted once
        for k, r in enumerate(ids):
            peers = [p for p in ids if p != r]
            for kind in ("descriptor", "pose"):
                inbox = team[r].gather(t, kind, peers, deadline_s=10.0)
                assert inbox.degradations == [] and sorted(inbox.messages) == peers
                for p in peers:
                    frame = frames_of(ids.index(p), t)[kind]
                    got, want = inbox.message(p), decode(frame)
                    assert inbox.messages[p].nbytes == len(frame)
                    assert got.sender == want.sender and got.step == t
                    if kind == "pose":
                        np.testing.assert_array_equal(got.T_odom_cam, want.T_odom_cam)
                    else:
                        np.testing.assert_array_equal(got.descriptor, want.descriptor)
    assert team["r0"].stats["wire_bytes_pose"] == 4 * (len(frames_of(0, 0)["pose"]) + len(w.HEADER))


def test_frames_of_later_steps_wait_and_earlier_are_late(team_of):
    team = team_of(["r0", "r1"])
    team["r1"].broadcast("descriptor", frames_of(1, 1)["descriptor"])  # step 1 before step 0
    inbox = team["r0"].gather(0, "descriptor", ["r1"], deadline_s=5.0)  # r1 is past 0: not waited for
    assert inbox.messages == {} and inbox.degradations == ["msg:lost"]
    assert team["r0"].gather(1, "descriptor", ["r1"], 5.0).message("r1").step == 1
    team["r1"].broadcast("pose", frames_of(1, 0)["pose"])
    t_end = time.monotonic() + 0.3 + SLACK_S  # until the late frame has come (a loaded machine may take longer)
    while team["r0"].stats["late"] < 1 and time.monotonic() < t_end:
        team["r0"].poll(0.05)
    assert team["r0"].gather(1, "pose", ["r1"], 0.3).degradations == ["msg:lost"]
    assert team["r0"].stats["late"] == 1
    with pytest.raises(ZenohLinkError, match="step 0 begun after step 1"):
        team["r0"].gather(0, "pose", ["r1"], 0.1)


# --------------------------------------------------------------------------- request / reply
class serving:
    """Answer ``link``'s image queries in a thread (as a robot does inside its waits) until the block ends."""

    def __init__(self, link: ZenohLink) -> None:
        self.stop = threading.Event()
        self.th = threading.Thread(target=lambda: [link.poll(0.05) for _ in iter(self.stop.is_set, True)],
                                   daemon=True)

    def __enter__(self):
        self.th.start()

    def __exit__(self, *exc):
        self.stop.set()
        self.th.join(10)


def reply_of(k: int, t: int) -> bytes:
    return ImageReply(k, t, b"\xff\xd8jpeg-bytes-%d" % t, (500.0, 500.0, 320.0, 240.0)).encode()


def test_request_reply_through_queryables(team_of):
    team = team_of(["r0", "r1", "r2"])
    asked = []
    for r in ("r1", "r2"):
        team[r].begin(3)

        def handler(peer, req, k=team.roster.index(r)):
            asked.append((peer, req))
            return reply_of(k, req.step) if req.step == 3 else None  # only the current image is held

        team[r].serve(handler)
    reqs = {p: ImageRequest(0, 3, team.roster.index(p)).encode() for p in ("r1", "r2")}
    team["r0"].begin(3)
    with serving(team["r1"]), serving(team["r2"]):
        inbox = team["r0"].request(3, reqs, deadline_s=5.0)
    assert inbox.sent == {p: len(f) for p, f in reqs.items()} and inbox.degradations == []
    for k, p in ((1, "r1"), (2, "r2")):
        assert inbox.messages[p].nbytes == len(reply_of(k, 3)) and inbox.message(p) == decode(reply_of(k, 3))
    assert sorted((peer, req.target) for peer, req in asked) == [("r0", 1), ("r0", 2)]


def test_image_no_longer_held_and_bad_requests(team_of):
    team = team_of(["r0", "r1", "r2"])
    team["r1"].serve(lambda peer, req: None)  # holds nothing
    team["r1"].begin(5)
    team["r0"].begin(5)
    with serving(team["r1"]):
        inbox = team["r0"].request(5, {"r1": ImageRequest(0, 5, 1).encode()}, deadline_s=5.0)
        assert inbox.messages == {} and inbox.degradations == ["msg:image-not-held"]
        raw = raw_session(team.ports["r1"])
        try:  # a request meant for r2 on r1's key, and one that is not a request: refused, counted by r1
            for frame in (ImageRequest(0, 5, 2).encode(), frames_of(0, 5)["pose"]):
                replies = list(raw.get(w.image_key("t", "r1"), payload=frame, attachment=w.HEADER, timeout=5.0))
                assert w.parse_error_payload(replies[0].err.payload.to_bytes()) in ("wrong-target", "garbled")
        finally:
            raw.close()
    assert team["r1"].stats["queries_refused_wrong-target"] == 1
    assert team["r1"].stats["queries_refused_garbled"] == 1
    assert team["r1"].take_degradations() == ["msg:garbled", "msg:garbled"]
    with pytest.raises(ZenohLinkError, match="not this robot's image request"):
        team["r0"].request(5, {"r1": ImageRequest(0, 5, 2).encode()}, 1.0)


def test_request_of_a_later_step_waits_until_the_owner_begins_it(team_of):
    team = team_of(["r0", "r1"])
    steps = []
    team["r1"].serve(lambda peer, req: steps.append(req.step) or reply_of(1, req.step))
    team["r1"].begin(1)
    team["r0"].begin(2)
    result = {}
    th = threading.Thread(target=lambda: result.update(
        inbox=team["r0"].request(2, {"r1": ImageRequest(0, 2, 1).encode()}, deadline_s=10.0)))
    th.start()
    team["r1"].poll(0.5)
    assert steps == []  # r1 is still at step 1
    team["r1"].begin(2)
    t_end = time.monotonic() + 10.0  # answered inside r1's waits: r1 keeps calling the link until r0 has it
    while th.is_alive() and time.monotonic() < t_end:
        team["r1"].poll(0.05)
    th.join(1)
    assert steps == [2] and result["inbox"].message("r1").step == 2


def test_request_to_a_peer_that_does_not_serve_costs_at_most_the_deadline(team_of):
    team = team_of(["r0", "r1", "r2"], up=["r0", "r1"])
    t0 = time.monotonic()
    inbox = team["r0"].request(0, {"r2": ImageRequest(0, 0, 2).encode()}, deadline_s=0.5)  # r2 is not up
    assert inbox.messages == {} and time.monotonic() - t0 < 0.5 + SLACK_S
    t0 = time.monotonic()
    inbox2 = team["r0"].request(0, {"r1": ImageRequest(0, 0, 1).encode()}, deadline_s=0.5)  # r1 never serves
    assert inbox2.messages == {} and 0.5 <= time.monotonic() - t0 < 0.5 + SLACK_S
    assert inbox.degradations == inbox2.degradations == ["msg:lost"]


def test_two_robots_requesting_from_each_other_do_not_deadlock(team_of):
    team = team_of(["r0", "r1"])
    out = {}
    for r in ("r0", "r1"):
        team[r].serve(lambda peer, req, k=team.roster.index(r): reply_of(k, req.step))

    def ask(r, p):
        out[r] = team[r].request(0, {p: ImageRequest(team.roster.index(r), 0, team.roster.index(p)).encode()}, 10.0)
        # queries are answered inside the link's waits: a robot whose own replies came first goes on
        # calling the link (the engine's next gather), modelled here by polling until the other is done
        t_end = time.monotonic() + 10.0
        while p not in out and time.monotonic() < t_end:
            team[r].poll(0.05)

    ths = [threading.Thread(target=ask, args=pair) for pair in (("r0", "r1"), ("r1", "r0"))]
    for th in ths:
        th.start()
    for th in ths:
        th.join(15)
    assert out["r0"].message("r1").sender == 1 and out["r1"].message("r0").sender == 0


# --------------------------------------------------------------------------- deadlines
def test_missing_peer_costs_at_most_the_deadline_then_nothing(team_of):
    team = team_of(["r0", "r1", "r2"], up=["r0", "r1"])
    lost = []
    for t in range(4):
        team["r1"].broadcast("descriptor", frames_of(1, t)["descriptor"])
        t0 = time.monotonic()
        inbox = team["r0"].gather(t, "descriptor", ["r1", "r2"], deadline_s=1.5)  # not waiting: well under it
        took = time.monotonic() - t0
        assert took < 1.5 + SLACK_S and inbox.message("r1") is not None
        lost.append((inbox.degradations, took >= 1.5))
    # r2 never appeared: waited for in steps 0 and 1 (it could still start: max_lag_steps = 2), then not
    assert [d for d, _ in lost] == [["msg:lost"]] * 4
    assert [waited for _, waited in lost] == [True, True, False, False]


def test_killed_peer_is_counted_and_not_waited_for(team_of, tmp_path):
    team = team_of(["r0", "r1"], up=["r0"])
    port = team.ports["r1"]
    code = ("import sys, time; sys.path.insert(0, %r)\n"
            "from cerpe.online.zenoh_link import ZenohLink\n"
            "link = ZenohLink('r1', ['r0', 'r1'], {'team': 't', 'multicast_scouting': False, "
            "'listen': ['tcp/127.0.0.1:%d'], 'connect': ['tcp/127.0.0.1:%d']}); link.announce()\n"
            "print('up', flush=True); time.sleep(60)\n") % (str(TESTS.parent), port, team.ports["r0"])
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "up"
        assert team["r0"].wait_peers(["r1"], 10.0) == []
        proc.kill()
        proc.wait(10)
        t0 = time.monotonic()
        while "r1" in team["r0"].present and time.monotonic() - t0 < 15:
            team["r0"].poll(0.1)
        t0 = time.monotonic()
        lost = team["r0"].gather(0, "descriptor", ["r1"], deadline_s=5.0).degradations
        lost += team["r0"].gather(0, "pose", ["r1"], deadline_s=5.0).degradations
        assert time.monotonic() - t0 < 5.0  # a peer known gone is not waited for (both gathers in less than one deadline)
        assert sorted(lost) == ["msg:lost", "msg:lost", "net:peer-lost"]
    finally:
        proc.kill()


def test_peer_that_said_bye_is_not_lost(team_of):
    team = team_of(["r0", "r1"])
    team["r1"].close(linger_s=0.0)
    t0 = time.monotonic()
    while "r1" in team["r0"].present and time.monotonic() - t0 < 30:  # generous: a loaded machine is slow
        team["r0"].poll(0.1)
    assert "r1" not in team["r0"].present, "r0 never heard r1's bye"
    inbox = team["r0"].gather(0, "pose", ["r1"], deadline_s=5.0)
    assert inbox.degradations == ["msg:lost"]  # its frame is missing, but no net:peer-lost


# --------------------------------------------------------------------------- bad input on our keys
def test_malformed_payloads_on_our_keys_are_counted(team_of):
    team = team_of(["r0", "r1"])
    raw = raw_session(team.ports["r0"])
    try:
        good = frames_of(1, 0)
        key = w.data_key("t", "r1", "descriptor")
        time.sleep(0.3)  # the raw session learns r0's subscriber
        raw.put(key, b"not a cerpe frame", attachment=w.HEADER)                    # garbled
        raw.put(key, good["descriptor"][:-1] + b"\x00", attachment=w.HEADER)       # bad checksum
        raw.put(key, good["descriptor"])                                           # no header
        raw.put(w.data_key("t", "r1", "pose"), good["descriptor"], attachment=w.HEADER)  # wrong key kind
        raw.put(w.data_key("t", "r1", "gossip"), good["descriptor"], attachment=w.HEADER)  # unknown kind
        raw.put(w.data_key("t", "r7", "descriptor"), good["descriptor"], attachment=w.HEADER)  # not in roster
        raw.put(key, frames_of(0, 0)["descriptor"], attachment=w.HEADER)           # sender index 0 on r1's key
        raw.put(key, good["descriptor"], attachment=w.HEADER)                      # finally the real one
        inbox = team["r0"].gather(0, "descriptor", ["r1"], deadline_s=5.0)
    finally:
        raw.close()
    assert inbox.message("r1") is not None
    assert sorted(inbox.degradations) == ["msg:garbled"] * 5 + ["msg:unknown-sender"] * 2


def test_other_protocol_version_is_one_counted_degradation(team_of, caplog):
    team = team_of(["r0", "r1"])
    raw = raw_session(team.ports["r0"])
    from cerpe.messages import VERSION

    other = w.MAGIC + bytes([w.LINK_PROTOCOL + 1, VERSION])
    try:
        token = raw.liveliness().declare_token(f"cerpe/t/r1/alive/v{w.LINK_PROTOCOL + 1}.{VERSION}/{raw.zid()}")
        time.sleep(0.3)
        for t in range(3):
            raw.put(w.data_key("t", "r1", "pose"), frames_of(1, t)["pose"], attachment=other)
        with caplog.at_level("WARNING"):
            inbox = team["r0"].gather(0, "pose", ["r1"], deadline_s=0.5)
        token.undeclare()
    finally:
        raw.close()
    assert inbox.degradations.count("link:protocol-mismatch") == 1
    assert team["r0"].stats["frames_foreign_protocol"] == 3
    assert (f"speaks cerpe link protocol v{w.LINK_STAMPS}.{VERSION} (by stamps), this robot "
            f"v{w.LINK_PROTOCOL}.{VERSION} (lock-step)" in caplog.text)


def test_robot_of_another_team_is_named_and_counted(team_of, caplog):
    with caplog.at_level("WARNING"):
        team = team_of(["r0", "r1"], teams={"r1": "lab-b"}, team="lab-a")
        t0 = time.monotonic()
        while not team["r0"].stats["link:team-mismatch"] and time.monotonic() - t0 < 10:
            team["r0"].poll(0.1)
        team["r1"].broadcast("descriptor", frames_of(1, 0)["descriptor"])  # on lab-b's keys: r0 never sees it
        inbox = team["r0"].gather(0, "descriptor", ["r1"], deadline_s=0.5)
    assert sorted(inbox.degradations) == ["link:team-mismatch", "msg:lost"]
    assert "robot r1 is up in team 'lab-b', this robot is in team 'lab-a'" in caplog.text


# --------------------------------------------------------------------------- sessions that cannot open
@pytest.mark.parametrize("conf, match", [
    ({"listen": ["tcp/10.255.255.1:7447"]}, "cannot open .*Cannot assign requested address"),
    ({"listen": ["nonsense"]}, "zenoh config listen/endpoints"),
    ({"zenoh": {"no/such/key": 1}}, "zenoh config no/such/key"),
    ({"mode": "client", "connect": ["tcp/127.0.0.1:1"]}, "cannot open .*Unable to connect"),
    ({"mode": "client"}, "needs a router endpoint"),
    ({"mode": "router"}, "expected one of"),
    ({"connect": "tcp/127.0.0.1:1"}, "expected a list of endpoints"),
    ({"team": "a/b"}, "--team 'a/b'"),
])
def test_session_that_cannot_open_gives_one_clear_error(conf, match):
    with pytest.raises(CerpeError, match=match):  # ZenohLinkError, or ZenohWireError for a bad name
        ZenohLink("r0", ["r0", "r1"], {"multicast_scouting": False, **conf})


def test_bad_link_options():
    with pytest.raises(ConfigError, match="unknown option"):
        ZenohLink("r0", ["r0"], {"tean": "x"})
    with pytest.raises(ZenohLinkError, match="roster"):
        ZenohLink("r2", ["r0", "r1"], {"multicast_scouting": False})


# --------------------------------------------------------------------------- robots in subprocesses
def test_three_driver_processes_on_loopback(tmp_path):
    """Three processes exchange real frames for 4 steps; everything arrives, content checked."""
    ids = ["r0", "r1", "r2"]
    ports = dict(zip(ids, free_ports(3)))
    procs = []
    for k, r in enumerate(ids):
        cmd = [sys.executable, str(DRIVER), "--robot", r, "--roster", ",".join(ids), "--steps", "4",
               "--deadline", "5", "--listen", endpoint(ports[r]), "--out", str(tmp_path / f"{r}.json")]
        for q in ids[:k]:
            cmd += ["--connect", endpoint(ports[q])]
        procs.append(subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
    for p in procs:
        out, _ = p.communicate(timeout=90)
        assert p.returncode == 0, out
    for r in ids:
        rep = json.loads((tmp_path / f"{r}.json").read_text())
        assert rep["expected"] == 4 * 3 * 2 and rep["received"] == rep["expected"], rep
        assert rep["bad_content"] == 0 and rep["degradations"] == {}, rep


def test_sending_on_a_closed_session_is_one_clear_error(team_of):
    team = team_of(["r0", "r1"])
    team["r0"].session.close()
    with pytest.raises(ZenohLinkError, match="robot r0: cannot send its pose"):
        team["r0"].broadcast("pose", frames_of(0, 0)["pose"])
    with pytest.raises(ZenohLinkError, match="robot r0: cannot send its image request to r1"):
        team["r0"].request(0, {"r1": ImageRequest(0, 0, 1).encode()}, 0.1)
