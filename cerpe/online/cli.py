"""Run ONE robot of a team online: this process talks to its peers over TCP.

Usage (one command per robot/machine; the same manifest and encounter on every one)::

    cerpe online --robot r0 --listen 0.0.0.0:7000 --peer r1=10.0.0.2:7000 \\
        --manifest datasets_manifest/synthetic-cad.yaml --encounter cad-l0-s0-e00 --rate 10

The robot replays its own frames of ENCOUNTER from MANIFEST (``--rate`` frames
per second; 0 = as fast as the team allows), exchanges descriptors, image
requests/replies and poses with the robots given by ``--peer`` (ID=HOST:PORT,
repeatable) and writes its own run folder in the format of ``cerpe run``
(``run.json``, ``<encounter>/steps.csv`` with this robot as ego,
``robots.csv``, ``poses/``, ``odometry/``, ``DONE.json``) plus
``<encounter>/online.json`` (network counters: frames lost, garbled, late, wait
time, bytes really written per kind). Other robots' images are never read; their
ground truth is (for the gt columns), so every machine needs the manifest's
trajectory files.

Robots start when all peers are connected (or after ``--connect-timeout``; a
peer that is not up yet is redialed with backoff). At each phase a robot waits
at most ``--timeout`` seconds for its peers' frames of the same step, then goes
on and counts what is missing (``msg:lost``); a peer that disappears is logged
and counted (``net:peer-lost``) and the robot continues alone (propagation, then
no estimate). See ``docs/ARCHITECTURE.md``, "Online transport".
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any, Iterator, Mapping

from ..pipeline import run as rp
from .net import Address, NetTransport, OnlineError, parse_address, parse_peer, resolve
from .node import RobotNode
from .node import default_conf as node_defaults

log = logging.getLogger(__name__)


def _encounter(setting: Any, name: str, manifest: Path) -> Any:
    for enc in setting.encounters:
        if enc.name == name:
            return enc
    raise OnlineError(f"{manifest}: no encounter {name!r}; it has {[e.name for e in setting.encounters]}")


def _check_robots(enc: Any, robot: str, peers: Mapping[str, Address], manifest: Path) -> None:
    for what, rid in [("--robot", robot)] + [("--peer", p) for p in peers]:
        if rid not in enc.robot_ids:
            raise OnlineError(f"{what} {rid!r}: encounter {enc.name} of {manifest} has robots {enc.robot_ids}")
    if robot in peers:
        raise OnlineError(f"--peer {robot}: that is this robot itself (--robot {robot})")


def run_online(manifest: Path | str, encounter: str, robot: str, listen: Address, peers: Mapping[str, Address],
               out: Path | str, *, method: str = "cerpe", profile: str = "offline", seed: int = 0,
               node_conf: Mapping[str, Any] | None = None, overwrite: bool = False, progress: bool = True,
               setting: Any = None, plugins: Any = None, config: Any = None) -> Path:
    """Run robot ``robot`` of ``encounter`` online and write its run folder ``out``.

    ``setting``, ``plugins`` (an object with ``descriptor``, ``backbone``,
    ``depth``) and ``config`` (a :class:`~cerpe.algorithm.CerpeConfig`) may be
    given instead of being loaded (tests, embedding in a robot's own process).
    Raises :class:`OnlineError` / :class:`~cerpe.pipeline.run.RunError` naming
    the argument or file at fault.
    """
    from ..algorithm import CerpeConfig, RobotAgent
    from ..protocols import FrameContext

    if method not in rp.CERPE_METHODS:
        raise OnlineError(f"--method {method!r}: online runs support {list(rp.CERPE_METHODS)}")
    manifest = Path(manifest).resolve()
    setting = setting if setting is not None else rp.load_manifest_setting(manifest)
    enc = _encounter(setting, encounter, manifest)
    _check_robots(enc, robot, peers, manifest)
    for rid, addr in peers.items():
        resolve(addr, f"--peer {rid}")
    out = Path(out)
    done = out / enc.name / "DONE.json"
    if done.exists() and not overwrite:
        raise rp.RunError(f"{done}: this robot already finished encounter {enc.name}; "
                          f"use --overwrite to run it again (with its peers)")
    net = NetTransport(robot, listen)  # binds now: a port in use fails before models load
    try:
        if plugins is None:
            plugins, config, mconf = rp.cerpe_plugins_and_config(
                method, profile, getattr(setting, "metric_depth", None), getattr(setting, "metric_depth_options", None))
        else:
            config = config if config is not None else CerpeConfig()
            mconf = {"cerpe": rp.config_dict(config), "preset": "given", "plugins": "given"}
        nconf = {**node_defaults, **(node_conf or {})}
        run_conf = {"format": rp.RUN_FORMAT, "method": method, "profile": profile, "seed": int(seed),
                    "setting": setting.name, "encounters": [enc.name], "method_config": mconf,
                    "code": rp.code_hash(method), "online": {"robot": robot, "team": sorted([robot, *peers]),
                                                             "node": nconf}}
        fp = rp.fingerprint(run_conf)
        out.mkdir(parents=True, exist_ok=True)
        rp.atomic_write_json(out / "run.json", {
            "method": method, "label": rp.METHOD_LABELS[method] + " (online)", "fingerprint": fp,
            "config": run_conf, "metric_scale": getattr(setting, "metric_depth", None) != "none",
            "manifest": str(manifest), "package_versions": rp.package_versions(),
            "git_revision": rp.git_revision(), "seed": int(seed), "profile": profile, "setting": setting.name,
            "command": " ".join(sys.argv), "listen": str(net.address),
            "peers": {p: str(a) for p, a in peers.items()}})
        k = enc.robot_ids.index(robot)
        agent = RobotAgent(robot, k, config, plugins.descriptor, plugins.backbone, plugins.depth)
        node = RobotNode(agent, enc.robot_ids, list(peers), net, nconf)
        net.connect(peers)
        stream = enc.robots[k]

        def frames() -> Iterator[tuple]:
            for t in range(enc.n_steps):
                yield stream.image(t), FrameContext(robot, t, stream.intrinsics, stream.depth_m(t), seed), \
                    float(stream.stamps_s[t])

        t0 = time.perf_counter()
        rp.run_encounter_to_folder(enc, lambda _enc: node.run(frames()), out / enc.name, fp, progress=progress)
        stats = {"node": dict(node.stats), "transport": dict(net.stats), "wall_time_s": time.perf_counter() - t0}
        rp.atomic_write_json(out / enc.name / "online.json", stats)
        log.info("robot %s: %s", robot, json.dumps({k: v for k, v in node.stats.items() if k != "wait_s"}))
    finally:
        net.close()
    return out


# --------------------------------------------------------------------------- CLI
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robot", required=True, help="this robot's id (a robot of the encounter, e.g. r0)")
    p.add_argument("--listen", required=True, help="HOST:PORT to accept peers on (e.g. 0.0.0.0:7000)")
    p.add_argument("--peer", action="append", default=[], metavar="ID=HOST:PORT",
                   help="a peer robot and where it listens (repeat per peer), e.g. r1=10.0.0.2:7000")
    p.add_argument("--manifest", required=True, type=Path, help="dataset manifest (the same on every robot)")
    p.add_argument("--encounter", required=True, help="encounter name in the manifest")
    p.add_argument("--out", type=Path, default=None,
                   help="run folder (default build/online/<manifest name>/<method>/<robot>)")
    p.add_argument("--method", default="cerpe", choices=rp.CERPE_METHODS, help="cerpe | cerpe-wo-em")
    p.add_argument("--profile", default="offline", help="backbone preset (default: offline)")
    p.add_argument("--rate", type=float, default=0.0, help="replay rate in frames/s (default 0: as fast as the team)")
    p.add_argument("--timeout", type=float, default=node_defaults["step_timeout_s"],
                   help="seconds to wait per phase for the peers' frames of the same step (default %(default)s)")
    p.add_argument("--connect-timeout", type=float, default=node_defaults["connect_timeout_s"],
                   help="seconds to wait for all peers before step 0 (default %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--overwrite", action="store_true", help="run again although this robot's folder is finished")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def main(args: argparse.Namespace) -> int:
    listen = parse_address(args.listen, "--listen")
    peers: dict[str, Address] = {}
    for text in args.peer:
        rid, addr = parse_peer(text)
        if rid in peers:
            raise OnlineError(f"--peer {rid}: given twice")
        peers[rid] = addr
    if not peers:
        raise OnlineError("no --peer given: an online robot needs at least one peer (ID=HOST:PORT)")
    for name, v in (("--rate", args.rate), ("--timeout", args.timeout), ("--connect-timeout", args.connect_timeout)):
        if not (v >= 0):
            raise OnlineError(f"{name} must be >= 0, got {v}")
    out = args.out
    if out is None:
        out = Path("build") / "online" / Path(args.manifest).stem / args.method / args.robot
    conf = {"step_timeout_s": args.timeout, "connect_timeout_s": args.connect_timeout, "rate_hz": args.rate}
    run_online(args.manifest, args.encounter, args.robot, listen, peers, out, method=args.method,
               profile=args.profile, seed=args.seed, node_conf=conf, overwrite=args.overwrite,
               progress=not args.no_progress)
    print(f"run folder: {out}")
    return 0
