"""Robots reading ROS 2 topics played from bags, against ``cerpe run`` on the same bags (real processes, loopback).

The bags are written from the development frames ``../shared/data/tum-fr1-xyz-10`` (robots as
``dev-tum-fr1-xyz`` makes them: forwards and backwards; a third from frame 1 on), or, where those
frames are absent, from the synthetic fixture encounters. The frames are re-timed
(``cerpe bag write --frame-rate``) to a rate a 2-core machine keeps up with, as a robot slower than
its camera would see them. Each robot is a ``cerpe online --input ros`` process (the offline models),
each bag a ``cerpe bag play`` process publishing it in real time on rmw_zenoh's keys.

* two robots: their estimates (evaluated against the bags' ground-truth topic, matched by stamp)
  against ``cerpe run`` through the ``rosbag`` adapter: e_rot within 1.2 times, success within 10 points;
* two and three robots: latency from an image's arrival to its estimates published, median and p90 per
  robot (printed; every robot met its peers and published).
"""
from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

zenoh = pytest.importorskip("zenoh")

from cerpe.datasets import load_setting  # noqa: E402
from cerpe.datasets.bag_write import write_encounter  # noqa: E402
from cerpe.online import zenoh_wire as w  # noqa: E402
from cerpe.pipeline import evaluate as ev  # noqa: E402
from cerpe.pipeline import run as rp  # noqa: E402
from cerpe.scene import Encounter  # noqa: E402
from test_online import _raw_conf  # noqa: E402
from test_online_zenoh_link import endpoint, free_ports  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TUM = ROOT.parent / "shared" / "data" / "tum-fr1-xyz-10"
ENV = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""), "OMP_NUM_THREADS": "1"}


def source_manifest(folder: Path, n_robots: int) -> Path:
    """The frames the bags are written from: TUM fr1/xyz robots, else a synthetic fixture encounter."""
    m = folder / f"src{n_robots}.yaml"
    if TUM.is_dir():
        third = "      - {id: mid, sequence: ., camera: fr1, frames: [1, 9]}\n" if n_robots == 3 else ""
        m.write_text(f"name: tum{n_robots}\nadapter: tum-rgbd\ndata_root: {TUM}\nmetric_depth: dataset\n"
                     f"association_tolerance_s: 0.02\nencounters:\n  - name: xyz\n    sync: index\n    robots:\n"
                     f"      - {{id: fwd, sequence: ., camera: fr1, frames: [0, 8]}}\n"
                     f"      - {{id: rev, sequence: ., camera: fr1, frames: [0, 8], reversed: true}}\n{third}")
    else:
        world = "cad-intersection" if n_robots == 2 else "indoor-team"
        m.write_text(f"name: synth{n_robots}\nadapter: synthetic\nworld: {world}\nsuite: fixture\nseed: 0\n"
                     f"metric_depth: sensor\ncache_dir: {folder / 'cache'}\n")
    return m


def bags_of(folder: Path, n_robots: int, frame_rate: float, n_frames: int = 8) -> tuple[Path, list[str], dict]:
    """Bags of the first ``n_frames`` frames of each robot, and the ``rosbag`` manifest reading them."""
    enc = load_setting(source_manifest(folder, n_robots)).encounters[0]
    n = min(n_frames, enc.n_steps)
    robots = [dataclasses.replace(r, stamps_s=r.stamps_s[:n], images=list(r.images[:n]), T_world_cam=r.T_world_cam[:n],
                                  depth=None if r.depth is None else list(r.depth[:n]),
                                  frame_ids=list(r.frame_ids[:n])) for r in enc.robots]
    enc = Encounter(enc.name, robots, None if enc.overlap is None else enc.overlap[:n], enc.meta)
    bags, manifest = write_encounter(enc, folder / "bags", frame_rate=frame_rate)
    return manifest, enc.robot_ids, bags


def wait_for_tokens(session, team: str, robots: list[str], timeout_s: float) -> None:
    """Until every robot's liveliness token is up (its models loaded, its topics subscribed)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        up = {w.parse_alive_key(str(r.ok.key_expr))[1] for r in session.liveliness().get(f"cerpe/{team}/*/alive/**")
              if r.ok is not None}
        if set(robots) <= up:
            return
        time.sleep(0.5)
    raise AssertionError(f"robots {robots} not up after {timeout_s} s")


def run_team(folder: Path, manifest: Path, robots: list[str], bags: dict[str, Path], team: str,
             registration: str = "worker") -> dict[str, Path]:
    """Robots with --input ros, then one bag player each, started together; returns the robots' run folders."""
    ports = dict(zip(robots + ["obs"], free_ports(len(robots) + 1)))
    eps = [endpoint(ports[r]) for r in robots]
    procs = {}
    for k, r in enumerate(robots):
        cmd = [sys.executable, "-m", "cerpe.cli", "online", "--robot", r, "--input", "ros", "--manifest", str(manifest),
               "--team", team, "--no-multicast", "--listen", eps[k], "--no-progress", "--out", str(folder / "on" / r),
               "--depth-topic", "camera/depth/image_raw", "--idle-exit", "3", "--reply-timeout", "5",
               "--registration", registration]
        for ep in eps[:k] + [endpoint(ports["obs"])]:
            cmd += ["--connect", ep]
        procs[r] = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=ENV)
    observer = zenoh.open(_raw_conf([], [endpoint(ports["obs"])]))
    try:
        wait_for_tokens(observer, team, robots, 240)
        start = time.time() + 4.0  # the players' sessions reach every robot first
        for r in robots:
            cmd = [sys.executable, "-m", "cerpe.cli", "bag", "play", str(bags[r]), "--robot", r, "--no-multicast",
                   "--start-at", f"{start:.3f}"] + [a for ep in eps for a in ("--connect", ep)]
            procs[f"play-{r}"] = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                                  env=ENV)
        logs = {name: p.communicate(timeout=240)[0] for name, p in procs.items()}
    finally:
        observer.close()
        for p in procs.values():
            if p.poll() is None:
                p.kill()
                p.wait()
    for name, p in procs.items():
        assert p.returncode == 0, f"{name}:\n{logs[name]}"
    return {r: folder / "on" / r for r in robots}


def latency_lines(label: str, outs: dict[str, Path]) -> list[str]:
    """One line per robot; every robot met its peers, and some published estimates."""
    lines, published = [], 0
    for r, out in outs.items():
        rep = json.loads(next(out.glob("*/online.json")).read_text())
        lat = 1e3 * np.asarray(rep["latency_s"])
        assert rep["peers_met"] == sorted(set(outs) - {r}), (r, rep["peers_met"])
        published += rep["estimates_published"]
        dropped = rep["input"].get("input:frame-dropped", 0)
        figures = (f"median {np.median(lat):.0f} ms, p90 {np.percentile(lat, 90):.0f} ms" if lat.size
                   else "no frame with an estimate")
        lines.append(f"[{label}] {r}: {rep['n_steps']} frames taken ({dropped} dropped), {rep['estimates_published']} "
                     f"estimates published; latency image arrival -> estimates out: {figures}")
    assert published > 0, lines
    return lines


@pytest.mark.parametrize("registration", ["inline", "worker"])
def test_two_robots_on_live_topics_match_cerpe_run_on_the_bags(tmp_path, registration):
    """Inline, each frame's estimate is of that frame, as in ``cerpe run``; with the worker a
    registration lands at a later frame, so a robot's first frame with an image has no direct
    estimate yet (one frame of each robot's eight: 12.5 points of success more may be missed)."""
    manifest, robots, bags = bags_of(tmp_path, 2, frame_rate=1.0)
    outs = run_team(tmp_path, manifest, robots, bags, "bags2", registration)
    ref = rp.run_method(manifest, "cerpe", tmp_path / "ref", progress=False)
    online = ev.evaluate(list(outs.values())).iloc[0]
    offline = ev.evaluate([ref]).iloc[0]
    print(f"[bags, 2 robots, {manifest.stem}] online --input ros --registration {registration}: e_rot {online['e_rot_rad']:.4f} rad, success "
          f"{online['success_pct']:.1f} % over {online['n_frames']} frames; cerpe run on the bags: e_rot "
          f"{offline['e_rot_rad']:.4f} rad, success {offline['success_pct']:.1f} % over {offline['n_frames']} frames")
    for line in latency_lines("bags, 2 robots", outs):
        print(line)
    assert online["n_frames"] >= 0.5 * offline["n_frames"] and online["n_no_gt"] == 0
    assert online["e_rot_rad"] <= 1.2 * offline["e_rot_rad"]
    first_frame = 0.0 if registration == "inline" else 100.0 / (offline["n_frames"] / len(robots))
    assert abs(online["success_pct"] - offline["success_pct"]) <= 10.0 + first_frame
    steps = pd.concat([pd.read_csv(next(o.glob("*/steps.csv"))) for o in outs.values()])
    assert steps.loc[steps.source != "none", "sigma_rot_rad"].gt(0).all()  # the covariance published


@pytest.mark.slow  # the path is the two-robot test's; this adds the figures of a team of three
def test_three_robots_latency(tmp_path):
    manifest, robots, bags = bags_of(tmp_path, 3, frame_rate=1.0)
    outs = run_team(tmp_path, manifest, robots, bags, "bags3")
    for line in latency_lines("bags, 3 robots", outs):
        print(line)
