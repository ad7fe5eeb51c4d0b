"""Two robots in two network namespaces joined by a veth pair, optionally impaired with tc netem.

Each robot is a real ``cerpe online`` process (offline backbone preset, the synthetic cad
fixture, 12 steps) in its own namespace. Runs only as root where ``ip netns add`` works
(skipped cleanly otherwise); the lossy cases (10 % and 30 % loss, 50 ms delay each way) also
need the netem qdisc (skipped where the kernel has none, as on the development machine).
Checks: both robots finish every step, nothing hangs, every frame that did not arrive in time is
counted in the records as in the link's counters (``msg:lost``, ``msg:image-not-held``); without
loss nothing is lost. Prints per robot: steps, frames lost, bytes of our frames per step, the
bytes the veth really carried per step (Zenoh, TCP/IP, scouting and keep-alives included), step
latency median and p90.

The robots use explicit endpoints (r0 listens, r1 dials), except the ``multicast`` case, which
uses ``cerpe online``'s default discovery (UDP multicast scouting) inside the namespaces.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("zenoh")

TESTS = Path(__file__).resolve().parent
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


def veth_bytes(ns: str, dev: str) -> int:
    """Bytes the device has sent so far (``ip -s`` counters)."""
    info = json.loads(_ip("-n", ns, "-j", "-s", "link", "show", "dev", dev).stdout)
    return int(info[0]["stats64"]["tx"]["bytes"])


def run_pair(pair: VethPair, manifest: Path, out: Path, tag: str, timeout_s: float,
             multicast: bool) -> dict[str, dict]:
    procs = {}
    devs = {"r0": "v0", "r1": "v1"}
    before = {r: veth_bytes(pair.ns[r], devs[r]) for r in devs}
    for r in ("r0", "r1"):
        cmd = ["ip", "netns", "exec", pair.ns[r], sys.executable, "-m", "cerpe.cli", "online", "--robot", r,
               "--manifest", str(manifest), "--team", f"ns{tag}", "--timeout", str(timeout_s),
               "--connect-timeout", "60", "--linger", "5", "--out", str(out / r), "--no-progress",
               "--zenoh", "transport/shared_memory/enabled=false",  # two machines share no memory
               "--lockstep"]  # every frame of every step is expected: each missing one is counted
        if not multicast:
            cmd += ["--no-multicast"]
            cmd += ["--listen", f"tcp/{ADDR['r0']}:{PORT}"] if r == "r0" else ["--connect", f"tcp/{ADDR['r0']}:{PORT}"]
        env = {**os.environ, "PYTHONPATH": str(TESTS.parent)}
        procs[r] = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    try:
        for r, p in procs.items():
            log, _ = p.communicate(timeout=300)
            assert p.returncode == 0, f"robot {r} failed:\n{log}"
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
    reps = {}
    for r in procs:
        enc = next((out / r).glob("*/DONE.json")).parent
        rob = pd.read_csv(enc / "robots.csv", dtype={"degradations": str}, keep_default_na=False)
        reps[r] = {**json.loads((enc / "online.json").read_text()), "robot": r,
                   "records": Counter(d for ds in rob["degradations"] for d in (ds.split(";") if ds else [])),
                   "veth_bytes": veth_bytes(pair.ns[r], devs[r]) - before[r]}
    return reps


def figures(rep: dict) -> str:
    link, n = rep["link"], rep["n_steps"]
    lat = np.asarray(rep["step_s"]) * 1e3
    lost = link.get("msg:lost", 0) + link.get("msg:image-not-held", 0)
    wire = {k[len("wire_bytes_"):]: v / n for k, v in sorted(link.items()) if k.startswith("wire_bytes_")}
    return (f"{rep['robot']}: {n} steps, {lost} frames lost (late after their deadline: {link.get('late', 0)}), "
            f"{sum(wire.values()):.0f} B/step of frames ({', '.join(f'{k} {v:.0f}' for k, v in wire.items())}), "
            f"{rep['veth_bytes'] / n:.0f} B/step sent on the veth, "
            f"step latency median {np.median(lat):.0f} ms, p90 {np.percentile(lat, 90):.0f} ms")


CASES = [  # tag, loss %, delay ms, multicast, needs netem
    ("lossless", 0, 0, False, False),
    ("multicast", 0, 0, True, False),
    ("loss10", 10, 50, False, True),
    ("loss30", 30, 50, False, True),
]


@pytest.fixture(scope="module")
def manifest(tmp_path_factory) -> Path:
    """The synthetic cad fixture (2 robots, 12 steps), rendered before the robots start."""
    m = tmp_path_factory.mktemp("netns") / "cad.yaml"
    m.write_text(f"name: netns-cad\nadapter: synthetic\nworld: cad-intersection\nsuite: fixture\nseed: 0\n"
                 f"metric_depth: sensor\ncache_dir: {m.parent / 'cache'}\n")
    from cerpe.pipeline.run import load_manifest_setting

    load_manifest_setting(m)
    return m


@pytest.mark.skipif(NO_NETNS is not None, reason=f"network namespaces: {NO_NETNS}")
@pytest.mark.parametrize("tag, loss_pct, delay_ms, multicast, needs_netem", CASES, ids=[c[0] for c in CASES])
def test_two_robots_in_network_namespaces(manifest, tmp_path, tag, loss_pct, delay_ms, multicast, needs_netem):
    if needs_netem and not _PROBE.get("netem"):
        pytest.skip("the kernel has no netem qdisc (tc qdisc add ... netem fails)")
    with VethPair(tag[:3], loss_pct, delay_ms) as pair:
        reps = run_pair(pair, manifest, tmp_path, tag[:3], 1.0 if needs_netem else 30.0, multicast)
    for rep in reps.values():
        print(f"[netns {tag}: loss {loss_pct} %, delay {delay_ms} ms] {figures(rep)}")
        link, records = rep["link"], rep["records"]
        assert rep["n_steps"] == 12 and rep["missing_at_start"] == []
        assert link.get("net:peer-lost", 0) == 0
        # every frame that did not arrive in time is counted, and it is in the records
        for name in ("msg:lost", "msg:image-not-held", "msg:garbled"):
            assert records.get(name, 0) == link.get(name, 0), (name, records, link)
        assert link.get("msg:lost", 0) <= 12 * 2 + link.get("frames_sent_request", 0)
        assert rep["veth_bytes"] > sum(v for k, v in link.items() if k.startswith("wire_bytes_"))
        if not loss_pct:
            assert link.get("msg:lost", 0) == 0 and link.get("msg:garbled", 0) == 0
