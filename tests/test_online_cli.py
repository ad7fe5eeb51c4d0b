"""The real ``cerpe online --lockstep`` command: one robot process each, on loopback, on the synthetic fixture suite.

Robots use explicit tcp/127.0.0.1 endpoints on free ports with multicast scouting off
(each listens on its port; all dial r0 only, as the README shows: Zenoh's gossip
connects the others with each other), the offline backbone
preset, and a render cache of their own that none of them finds rendered: they start
together, so the machine lock around loading the manifest is exercised too.

* 2 robots (cad fixture) and 3 robots (indoor fixture), lossless: every robot's rows
  of ``steps.csv`` and ``robots.csv`` equal ``cerpe run``'s on the same manifest (all
  columns but the stage timings), and the figures of the run are printed (steps,
  frames lost, bytes on the wire per robot per step, step latency median / p90 online
  against the robot's compute time in the in-process run). Timings are wall clock on a
  shared machine: indicative only. `cerpe eval` of the robots' folders together gives
  the table of the `cerpe run` folder; of one robot's folder, that robot's rows with a
  success after co-visibility.
* A robot process killed mid-run (SIGKILL) is counted once (``net:peer-lost``) by the
  others, which finish without waiting for it.
* Bad peers around a running robot: another protocol version, another team, a second
  session with its id, garbage on its keys, a query for an image it no longer holds:
  counted or answered "not held", never a hang; the robot, which never met a peer,
  finishes with a warning and exit code 4; bad options and a session that cannot
  open: one line on stderr, exit code 2.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

zenoh = pytest.importorskip("zenoh")

from cerpe.messages import VERSION, ImageRequest, decode  # noqa: E402
from cerpe.online import zenoh_wire as w  # noqa: E402
from cerpe.online.cli import EXIT_NO_PEER  # noqa: E402
from cerpe.pipeline import evaluate as ev  # noqa: E402
from cerpe.pipeline import run as rp  # noqa: E402
from test_online import _raw_conf  # noqa: E402
from test_online_zenoh_link import endpoint, free_ports  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
WORLDS = {"cad": ("cad-intersection", 2), "indoor": ("indoor-team", 3)}


@pytest.fixture(scope="module")
def manifests(tmp_path_factory) -> dict[str, Path]:
    """Synthetic fixture manifests whose render cache is empty (the first robots to start render it)."""
    root = tmp_path_factory.mktemp("online-cli")
    out = {}
    for name, (world, _) in WORLDS.items():
        m = root / f"{name}.yaml"
        m.write_text(f"name: online-{name}\nadapter: synthetic\nworld: {world}\nsuite: fixture\nseed: 0\n"
                     f"metric_depth: sensor\ncache_dir: {root / 'cache'}\n")
        out[name] = m
    return out


def robot_cmd(manifest: Path, robot: str, out: Path, team: str, listen: str, connect: list[str],
              *extra: str) -> list[str]:
    cmd = [sys.executable, "-m", "cerpe.cli", "online", "--robot", robot, "--manifest", str(manifest),
           "--team", team, "--no-multicast", "--listen", listen, "--out", str(out / robot), "--no-progress",
           "--lockstep"]
    for ep in connect:
        cmd += ["--connect", ep]
    return cmd + list(extra)


def launch(manifest: Path, robots: list[str], out: Path, team: str, *extra: str,
           also_connect: tuple[str, ...] = ()) -> dict[str, subprocess.Popen]:
    ports = dict(zip(robots, free_ports(len(robots))))
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    procs = {}
    for k, r in enumerate(robots):
        cmd = robot_cmd(manifest, r, out, team, endpoint(ports[r]),  # a star: the others find each other
                        [endpoint(ports[robots[0]])] * (k > 0) + list(also_connect), *extra)  # through r0
        procs[r] = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    return procs


def finish(procs: dict[str, subprocess.Popen], timeout_s: float = 240) -> dict[str, tuple[int, str]]:
    out = {}
    try:
        for r, p in procs.items():
            log, _ = p.communicate(timeout=timeout_s)
            out[r] = (p.returncode, log)
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
                p.wait()
    return out


def figures(label: str, online_root: Path, ref_dir: Path, robots: list[str]) -> list[str]:
    """One line per robot: steps, frames lost, bytes on the wire per step, step latency online vs in process."""
    enc = next(p.parent.name for p in ref_dir.glob("*/DONE.json"))
    ref_robots = pd.read_csv(ref_dir / enc / "robots.csv")
    stage_cols = [c for c in ref_robots.columns if c.startswith("t_") and c.endswith("_s")]
    done = json.loads((ref_dir / enc / "DONE.json").read_text())
    team_ms = 1e3 * done["wall_time_s"] / done["n_steps"]
    lines = []
    for r in robots:
        rep = json.loads((online_root / r / enc / "online.json").read_text())
        link, n = rep["link"], rep["n_steps"]
        lost = sum(link.get(k, 0) for k in ("msg:lost", "msg:image-not-held"))
        wire = {k[len("wire_bytes_"):]: v / n for k, v in sorted(link.items()) if k.startswith("wire_bytes_")}
        lat = 1e3 * np.asarray(rep["step_s"])
        ref = 1e3 * ref_robots[ref_robots.robot == r][stage_cols].sum(axis=1).to_numpy()
        lines.append(f"[{label}] {r}: {n} steps, {lost} frames lost, {sum(wire.values()):.0f} B/step on the wire "
                     f"({', '.join(f'{k} {v:.0f}' for k, v in wire.items())}; frames + 4-byte header), "
                     f"step latency online median {np.median(lat):.0f} ms p90 {np.percentile(lat, 90):.0f} ms; "
                     f"in process (this robot's stages) median {np.median(ref):.0f} ms p90 "
                     f"{np.percentile(ref, 90):.0f} ms, team step {team_ms:.0f} ms")
    return lines


def _without_timings(df: pd.DataFrame) -> pd.DataFrame:
    return df[[c for c in df.columns if not (c.startswith("t_") and c.endswith("_s"))]].reset_index(drop=True)


@pytest.mark.parametrize("name", list(WORLDS))
def test_robot_processes_equal_cerpe_run(manifests, tmp_path, name):
    robots = [f"r{k}" for k in range(WORLDS[name][1])]
    res = finish(launch(manifests[name], robots, tmp_path / "online", f"eq{name}", "--timeout", "60",
                        "--connect-timeout", "120"))
    for r, (rc, log) in res.items():
        assert rc == 0, f"robot {r}:\n{log}"
    ref_dir = rp.run_method(manifests[name], "cerpe", tmp_path / "ref", progress=False)
    enc = next(p.parent.name for p in ref_dir.glob("*/DONE.json"))
    ref_steps, ref_robots = (pd.read_csv(ref_dir / enc / f) for f in ("steps.csv", "robots.csv"))
    for r in robots:
        d = tmp_path / "online" / r / enc
        steps, rob = pd.read_csv(d / "steps.csv"), pd.read_csv(d / "robots.csv")
        pd.testing.assert_frame_equal(_without_timings(steps), _without_timings(ref_steps[ref_steps.ego == r]),
                                      check_exact=False, check_dtype=False, rtol=0, atol=1e-9)
        pd.testing.assert_frame_equal(_without_timings(rob), _without_timings(ref_robots[ref_robots.robot == r]),
                                      check_exact=False, check_dtype=False, rtol=0, atol=1e-9)
        rep = json.loads((d / "online.json").read_text())
        assert rep["missing_at_start"] == [] and rep["link"].get("msg:lost", 0) == 0
        assert rep["link"].get("replies_sent", 0) > 0  # images went through the queryables
        meta = json.loads((tmp_path / "online" / r / "run.json").read_text())
        assert meta["label"] == "CERPE (online)" and meta["config"]["online"]["team"] == f"eq{name}"
    assert (ref_steps["bytes_pair"] > 0).any()
    # the team's folders together: the table of `cerpe run`; one robot's folder alone: its own rows, with
    # success after co-visibility (from its peers' overlap ground truth about it)
    team = [tmp_path / "online" / r for r in robots]
    pd.testing.assert_frame_equal(ev.evaluate(team, by="encounter"), ev.evaluate([ref_dir], by="encounter"))
    frames, _ = ev.evaluate_runs([ref_dir])
    for r in robots:
        alone = ev.evaluate([tmp_path / "online" / r]).iloc[0]
        mine = ev.summarise(frames[frames["ego"] == r], ["setting", "method"]).iloc[0]
        assert alone["n_frames"] == mine["n_frames"] and alone["n_frames_after_covis"] == mine["n_frames_after_covis"]
        np.testing.assert_allclose(alone["success_after_covis_pct"], mine["success_after_covis_pct"])
        assert json.loads((tmp_path / "online" / r / enc / "online.json").read_text())["peers_met"] == \
            [p for p in robots if p != r]
    for line in figures(f"loopback {len(robots)} robots", tmp_path / "online", ref_dir, robots):
        print(line)


def test_killed_robot_process_is_counted_and_the_others_finish(manifests, tmp_path):
    robots = ["r0", "r1", "r2"]
    (obs_port,) = free_ports(1)
    observer = zenoh.open(_raw_conf([], [endpoint(obs_port)]))
    procs: dict[str, subprocess.Popen] = {}
    killed = threading.Event()

    def on_pose(sample):  # r2 dies right after it published its pose of step 4
        msg = decode(sample.payload.to_bytes())
        if msg.step >= 4 and not killed.is_set() and "r2" in procs:
            procs["r2"].send_signal(signal.SIGKILL)
            killed.set()

    sub = observer.declare_subscriber(w.data_key("kill", "r2", "pose"), on_pose)
    try:
        procs.update(launch(manifests["indoor"], robots, tmp_path, "kill", "--timeout", "30", "--rate", "4",
                            "--connect-timeout", "120", "--linger", "2", also_connect=(endpoint(obs_port),)))
        res = finish(procs)
    finally:
        sub.undeclare()
        observer.close()
    assert killed.is_set() and res["r2"][0] == -signal.SIGKILL
    for r in ("r0", "r1"):
        assert res[r][0] == 0, f"robot {r}:\n{res[r][1]}"
        enc = next((tmp_path / r).glob("*/DONE.json")).parent
        rob = pd.read_csv(enc / "robots.csv", dtype={"degradations": str}, keep_default_na=False)
        degr = [d.split(";") if d else [] for d in rob["degradations"]]
        assert sum(ds.count("net:peer-lost") for ds in degr) == 1
        first = next(t for t, ds in enumerate(degr) if "net:peer-lost" in ds)
        assert 4 <= first <= 7
        for ds in degr[first + 1:]:  # r2's descriptor and pose are lost each later step; r1's (or r0's) arrive
            assert ds.count("msg:lost") == 2, degr
        steps = pd.read_csv(enc / "steps.csv")
        live = steps[(steps.other != "r2") & (steps.step > first)]
        assert len(live) == len(degr) - first - 1 and live["gate_score"].notna().all()
        rep = json.loads((enc / "online.json").read_text())
        assert rep["n_steps"] == len(degr) == 12
        assert max(rep["step_s"][first + 1:]) < 10  # no deadline (30 s) spent on a robot known gone


def test_bad_peers_around_a_running_robot_are_counted(manifests, tmp_path):
    """r0 runs alone in team 'bad'; a raw session plays every bad peer of issue 22 at once."""
    (obs_port,) = free_ports(1)
    raw = zenoh.open(_raw_conf([], [endpoint(obs_port)]))
    zid = str(raw.zid())
    other = w.MAGIC + bytes([w.LINK_PROTOCOL + 1, VERSION])
    tokens = [raw.liveliness().declare_token(f"cerpe/bad/r1/alive/v{w.LINK_PROTOCOL + 1}.{VERSION}/{zid}"),
              raw.liveliness().declare_token(f"cerpe/elsewhere/r1/alive/{w.PROTOCOL_TAG}/{zid}"),
              raw.liveliness().declare_token(f"cerpe/bad/r0/alive/{w.PROTOCOL_TAG}/{zid}")]
    seen: list[int] = []
    sub = raw.declare_subscriber(w.data_key("bad", "r0", "descriptor"),
                                 lambda s: seen.append(decode(s.payload.to_bytes()).step))
    procs = launch(manifests["cad"], ["r0"], tmp_path, "bad", "--timeout", "0.3", "--connect-timeout", "2",
                   "--rate", "3", "--linger", "0", also_connect=(endpoint(obs_port),))
    replies = []
    try:
        t0 = time.monotonic()
        while procs["r0"].poll() is None and time.monotonic() - t0 < 120:
            key = w.data_key("bad", "r1", "descriptor")
            raw.put(key, b"not a cerpe frame", attachment=w.HEADER)     # garbled payload
            raw.put(key, b"\x00" * 40)                                  # no header
            raw.put(w.data_key("bad", "r1", "pose"), b"x", attachment=other)  # another protocol version
            if seen and max(seen) >= 3 and not replies:  # r0 is past step 0: its image of step 0 is gone
                replies = list(raw.get(w.image_key("bad", "r0"), payload=ImageRequest(1, 0, 0).encode(),
                                       attachment=w.HEADER, timeout=10.0))
            time.sleep(0.2)
        res = finish(procs, 60)
    finally:
        for tok in tokens:
            tok.undeclare()
        sub.undeclare()
        raw.close()
    rc, log = res["r0"]
    assert rc == EXIT_NO_PEER, log  # r1 never came (only its impostors): finished, but said so
    assert "robot r0 never met any of its peers ['r1']" in log and "never met any peer" in log
    assert "speaks cerpe link protocol" in log and "is up in team 'elsewhere'" in log and "same id" in log
    assert [r.err.payload.to_bytes() for r in replies if r.err is not None] == [w.error_payload(w.NOT_HELD)]
    enc = next((tmp_path / "r0").glob("*/DONE.json")).parent
    rob = pd.read_csv(enc / "robots.csv", dtype={"degradations": str}, keep_default_na=False)
    degr = [d for ds in rob["degradations"] for d in (ds.split(";") if ds else [])]
    for name in ("link:protocol-mismatch", "link:team-mismatch", "link:duplicate-robot"):
        assert degr.count(name) == 1, (name, degr)
    assert degr.count("msg:garbled") >= 2
    # the stale request is refused by r0's engine (msg:stale-request, booked only when it comes during a step)
    rep = json.loads((enc / "online.json").read_text())
    assert rep["peers_met"] == []
    assert rep["link"]["queries_refused_not-held"] == 1 and degr.count("msg:stale-request") <= 1
    assert len(rob) == 12  # every step ran, r1 never came: its frames counted lost, no hang


def test_cli_errors_are_one_line(manifests):
    """Bad options and sessions that cannot open: exit 2, one line on stderr, no traceback, no hang."""
    cmd = [sys.executable, "-m", "cerpe.cli", "online", "--robot", "r0", "--manifest", str(manifests["cad"]),
           "--no-multicast", "--ros-keys", "off"]
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    for extra, match in [(["--listen", "nonsense"], "zenoh config listen/endpoints"),
                         (["--mode", "client", "--connect", "tcp/127.0.0.1:1"], "Zenoh session cannot open"),
                         (["--timeout", "-1"], "--timeout must be >= 0"),
                         (["--team", "a/b"], "--team 'a/b'"),
                         (["--robot", "r9"], "--robot 'r9'")]:  # more cases: test_online_zenoh_link, test_online
        proc = subprocess.run(cmd + extra, capture_output=True, text=True, timeout=120, env=env)
        assert proc.returncode == 2, (extra, proc.stderr)
        assert "Traceback" not in proc.stderr and match in proc.stderr, (extra, proc.stderr)
        assert [ln for ln in proc.stderr.splitlines() if ln.startswith("cerpe online: error")] != []
