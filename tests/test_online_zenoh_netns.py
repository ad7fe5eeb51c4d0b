"""Two robots in two network namespaces joined by a veth pair, optionally impaired with tc netem.

Each robot is a driver process (tests/zenoh_peer_driver.py) exchanging real cerpe frames step
by step over ZenohLink: descriptors, image request/reply through the owner's queryable, poses.
Runs only as root where ``ip netns add`` works (skipped cleanly otherwise); the lossy cases
(10 % and 30 % loss, 50 ms delay each way) also need the netem qdisc (skipped where the kernel
has none). Checks: frames flow, every frame that did not arrive is counted (``msg:lost`` or
``msg:image-not-held``), contents are right, nothing hangs. Prints per robot: steps, frames
lost, bytes per step, step latency median and p90.

The robots use explicit endpoints (r0 listens, r1 dials), except the ``multicast`` case, which
uses Zenoh's default discovery (UDP multicast scouting) inside the isolated namespaces.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("zenoh")

TESTS = Path(__file__).resolve().parent
DRIVER = TESTS / "zenoh_peer_driver.py"
ADDR = {"r0": "10.77.0.1", "r1": "10.77.0.2"}
PORT = 7447


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20, check=check)


def _why_no_netns() -> str | None:
    if os.name != "posix" or os.geteuid() != 0:
        return "needs root"
    if not (shutil.which("ip") and shutil.which("tc")):
        return "needs ip and tc (iproute2)"
    probe = f"czp{os.getpid()}"
    if _ip("netns", "add", probe, check=False).returncode != 0:
        return "ip netns add does not work here"
    try:
        r = subprocess.run(["ip", "netns", "exec", probe, "tc", "qdisc", "add", "dev", "lo", "root", "netem",
                            "delay", "1ms"], capture_output=True, text=True, timeout=20)
        _PROBE["netem"] = r.returncode == 0
    finally:
        _ip("netns", "del", probe, check=False)
    return None


_PROBE: dict[str, bool] = {}
NO_NETNS = _why_no_netns()


class VethPair:
    """Namespaces ``cz<pid><tag>a/b`` with ``v0``/``v1`` at 10.77.0.1/2, netem on both ends if asked."""

    def __init__(self, tag: str, loss_pct: float, delay_ms: float) -> None:
        base = f"cz{os.getpid()}{tag}"
        self.ns = {"r0": base + "a", "r1": base + "b"}
        self.loss_pct, self.delay_ms = loss_pct, delay_ms

    def __enter__(self) -> "VethPair":
        a, b = self.ns["r0"], self.ns["r1"]
        _ip("netns", "add", a)
        _ip("netns", "add", b)
        _ip("link", "add", "v0", "netns", a, "type", "veth", "peer", "name", "v1", "netns", b)
        for r, dev in (("r0", "v0"), ("r1", "v1")):
            ns = self.ns[r]
            _ip("-n", ns, "addr", "add", ADDR[r] + "/24", "dev", dev)
            _ip("-n", ns, "link", "set", dev, "up")
            _ip("-n", ns, "link", "set", "lo", "up")
            if self.loss_pct or self.delay_ms:
                subprocess.run(["ip", "netns", "exec", ns, "tc", "qdisc", "add", "dev", dev, "root", "netem",
                                "loss", f"{self.loss_pct}%", "delay", f"{self.delay_ms}ms"],
                               check=True, capture_output=True, timeout=20)
        # Zenoh picks its multicast interface when the session opens: start robots once the link is up
        deadline = time.monotonic() + 10
        while not all("state UP" in _ip("-n", self.ns[r], "-o", "link", "show", "dev", dev).stdout
                      for r, dev in (("r0", "v0"), ("r1", "v1"))):
            assert time.monotonic() < deadline, "the veth pair did not come up"
            time.sleep(0.05)
        return self

    def __exit__(self, *exc) -> None:
        for ns in self.ns.values():
            _ip("netns", "del", ns, check=False)


def run_pair(pair: VethPair, out: Path, steps: int, deadline_s: float, multicast: bool) -> dict[str, dict]:
    procs = {}
    for r in ("r0", "r1"):
        cmd = ["ip", "netns", "exec", pair.ns[r], sys.executable, str(DRIVER), "--robot", r, "--roster", "r0,r1",
               "--steps", str(steps), "--deadline", str(deadline_s), "--connect-timeout", "20",
               "--linger", "5", "--out", str(out / f"{r}.json")]
        if multicast:
            cmd.append("--multicast")
        elif r == "r0":
            cmd += ["--listen", f"tcp/{ADDR['r0']}:{PORT}"]
        else:
            cmd += ["--connect", f"tcp/{ADDR['r0']}:{PORT}"]
        env = {**os.environ, "PYTHONPATH": str(TESTS.parent)}
        procs[r] = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    try:
        for r, p in procs.items():
            log, _ = p.communicate(timeout=30 + steps * 3 * (deadline_s + 1))
            assert p.returncode == 0, f"robot {r} failed:\n{log}"
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
    return {r: json.loads((out / f"{r}.json").read_text()) for r in procs}


def figures(rep: dict) -> str:
    lat = np.asarray(rep["step_s"]) * 1e3
    lost = rep["expected"] - rep["received"]
    per_step = sum(rep["bytes_per_step"].values())
    return (f"{rep['robot']}: {rep['steps']} steps, {lost}/{rep['expected']} frames lost, "
            f"{per_step:.0f} B/step sent ({', '.join(f'{k} {v:.0f}' for k, v in rep['bytes_per_step'].items())}), "
            f"step latency median {np.median(lat):.1f} ms, p90 {np.percentile(lat, 90):.1f} ms, "
            f"degradations {rep['degradations']}")


CASES = [  # tag, loss %, delay ms, multicast, needs netem
    ("lossless", 0, 0, False, False),
    ("multicast", 0, 0, True, False),
    ("loss10", 10, 50, False, True),
    ("loss30", 30, 50, False, True),
]


@pytest.mark.skipif(NO_NETNS is not None, reason=f"network namespaces: {NO_NETNS}")
@pytest.mark.parametrize("tag, loss_pct, delay_ms, multicast, needs_netem", CASES, ids=[c[0] for c in CASES])
def test_two_robots_in_network_namespaces(tmp_path, tag, loss_pct, delay_ms, multicast, needs_netem):
    if needs_netem and not _PROBE.get("netem"):
        pytest.skip("the kernel has no netem qdisc (tc qdisc add ... netem fails)")
    steps, deadline_s = (6, 0.8) if needs_netem else (5, 2.0)
    with VethPair(tag[:3], loss_pct, delay_ms) as pair:
        reps = run_pair(pair, tmp_path, steps, deadline_s, multicast)
    for rep in reps.values():
        print(f"[netns {tag}: loss {loss_pct} %, delay {delay_ms} ms] {figures(rep)}")
        assert rep["missing_at_start"] == [] and rep["bad_content"] == 0
        assert rep["received"] > 0  # frames flow
        deg = rep["degradations"]
        # every frame that did not arrive is counted, once
        assert rep["expected"] - rep["received"] == deg.get("msg:lost", 0) + deg.get("msg:image-not-held", 0)
        if not loss_pct:
            assert rep["received"] == rep["expected"] and deg == {}
