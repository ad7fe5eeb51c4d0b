"""Run ONE robot of a team online: this process talks to its peers over Zenoh.

One command per robot (machine); the same manifest, encounter and --team on every one:

    cerpe online --robot r0 --manifest datasets_manifest/synthetic-indoor.yaml \\
        --encounter indoor-s0-e00 --rate 10

What it does: replays this robot's frames of ENCOUNTER from MANIFEST (--rate
frames per second; 0 = as fast as the team allows) and runs Algorithm 1 with its
peers, the other robots of the encounter: descriptors and poses are published on
Zenoh keys cerpe/<team>/<robot>/{descriptor,pose}, image requests are Zenoh
queries to the owner's cerpe/<team>/<robot>/image. Other robots' images are
never read; their ground truth is (for the gt columns), so every machine needs
the manifest's trajectory files. Wire format: docs/online.md.

Finding the peers: by default Zenoh peer mode with UDP multicast scouting
(224.0.0.224:7446) on the LAN: nothing to configure. Where multicast does not
pass (Wi-Fi, VPN, another subnet), let one robot listen on a fixed endpoint,
--listen tcp/0.0.0.0:7447, and give the others --connect tcp/<its IP>:7447
(add --no-multicast to rely on endpoints only). Robots start in any order; a
--connect endpoint that is not up yet is retried. With a Zenoh router (zenohd,
or ROS 2's rmw_zenohd), --mode client --connect tcp/<router>:7447. Firewall:
open the TCP port of --listen (Zenoh's 7447 by convention) and UDP 7446 for
multicast scouting. Robots of another --team, or of another cerpe protocol
version, are named in a warning and counted (link:team-mismatch,
link:protocol-mismatch), never mixed in.

Timing: a robot starts when all its peers are up (or after --connect-timeout).
At each phase of a step it waits at most --timeout seconds for its peers'
frames of the same step, then goes on and counts what is missing (msg:lost); a
peer whose session ends without saying bye is counted (net:peer-lost) and the
robot continues without it (propagation, then no estimate).

ROS 2: every step, each relative-pose estimate T_cj_ci (pose of this robot's
camera in robot j's camera, OpenCV/ROS optical axes, metres) is published as a
geometry_msgs/msg/PoseWithCovarianceStamped (CDR) for topic
/cerpe/<team>/<robot>/relative_pose/<j>, frame_id <team>/<j>/camera_optical,
stamp = the frame's capture time, covariance all zeros (unknown). --ros-keys
rmw_zenoh (default) puts it on rmw_zenoh's key <domain>/<topic>/<type>/<hash>
(--ros-domain, --ros-distro); ros2dds on the key zenoh-bridge-ros2dds uses;
off publishes nothing. --team and robot ids must then be ROS name tokens
(a letter, then letters, digits, '_').

Output: the run folder of `cerpe run` (cerpe.runfolder) with only this robot as ego (run.json,
<encounter>/steps.csv, robots.csv, poses/, odometry/, DONE.json) plus
<encounter>/online.json (link counters: frames and bytes sent per kind, losses,
late frames, waits; per-step wall times; estimates published; the peers met) and
<encounter>/peers_overlap.csv (the overlap ground truth of the peers' side of
each pair, for success after co-visibility). `cerpe eval` reads it: give it the
folders of every robot of the team to evaluate the team (the table `cerpe run`
gives), or one robot's folder for that robot.

Exit status: 0 when the run finished having met at least one peer; 4 when it
finished without ever meeting any peer (a warning says so: its folder holds no
inter-robot estimate; check --team, the endpoints and that the peers were
started); 2 for a bad option, an unknown robot or encounter, an --out that
cannot be written, or a Zenoh session that cannot open (bad endpoint, router
not reachable, address not on this machine): one line on stderr.
"""
from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import logging
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator, Mapping, NamedTuple

from .. import knobs
from ..atomicio import atomic_write_json, atomic_write_text, ensure_dir
from ..config import merge_conf
from ..methods import CERPE_METHODS, METHOD_LABELS
from ..runfolder import write
from ..runfolder.layout import DONE_JSON, PEER_OVERLAP_CSV, RunError
from ..runfolder.provenance import code_hash, config_dict
from . import ros, zenoh_session, zenoh_wire
from .node import ROS_KEYS, OnlineError, RobotNode
from .node import default_conf as node_defaults
from .zenoh_link import ZenohLink
from .zenoh_link import default_conf as link_defaults

log = logging.getLogger(__name__)

EXIT_NO_PEER = 4  # the run finished without ever meeting any peer (see the module doc)


class OnlineRun(NamedTuple):
    """What :func:`run_online` did: the run folder, the encounter, the peers this robot met."""

    out: Path
    encounter: str
    peers_met: list[str]


def _encounter(setting: Any, name: str | None, manifest: Path) -> Any:
    names = [e.name for e in setting.encounters]
    if name is None:
        if len(names) != 1:
            raise OnlineError(f"{manifest} has {len(names)} encounters {names}: choose one with --encounter")
        return setting.encounters[0]
    for enc in setting.encounters:
        if enc.name == name:
            return enc
    raise OnlineError(f"{manifest}: no encounter {name!r}; it has {names}")


@contextlib.contextmanager
def _machine_lock(manifest: Path) -> Iterator[None]:
    """Serialise loading ``manifest`` between the robot processes of one machine.

    A synthetic manifest renders its suite into a shared cache on first load; two
    robots started together would otherwise render into the same folder at once.
    """
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock (start the robots one after the other there)
        yield
        return
    key = hashlib.sha1(str(manifest).encode()).hexdigest()[:16]
    path = Path(tempfile.gettempdir()) / f"cerpe-online-{key}.lock"
    with open(path, "a+") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def run_online(manifest: Path | str, encounter: str | None, robot: str, out: Path | str, *,
               link_conf: Mapping[str, Any] | None = None, node_conf: Mapping[str, Any] | None = None,
               method: str = "cerpe", preset: str = "paper", seed: int = 0, overwrite: bool = False,
               progress: bool = True, setting: Any = None, plugins: Any = None, config: Any = None,
               sets: Mapping[str, Any] | None = None) -> OnlineRun:
    """Run robot ``robot`` of ``encounter`` online and write its run folder ``out``.

    ``link_conf``: options of :class:`~cerpe.online.zenoh_link.ZenohLink` (team,
    endpoints, mode, scouting); ``node_conf``: of :class:`~cerpe.online.node.RobotNode`
    (timeouts, rate, ROS keys). ``setting``, ``plugins`` (an object with
    ``descriptor``, ``backbone``, ``depth``) and ``config`` (a
    :class:`~cerpe.algorithm.AlgorithmConfig`) may be given instead of being loaded
    (tests, embedding in a robot's own process); ``preset``, ``sets``: the loaded configuration
    (``--preset``, ``--set``; every robot of a team should pass the same). Raises a
    :class:`~cerpe.errors.CerpeError` naming the argument, file or endpoint at fault.
    A robot that never met any peer is logged as a warning (``OnlineRun.peers_met`` empty).
    """
    from ..algorithm import AlgorithmConfig, RobotAgent
    from ..pipeline.cerpe_method import cerpe_plugins_and_config
    from ..pipeline.setting import load_manifest_setting
    from ..protocols import FrameContext

    if method not in CERPE_METHODS:
        raise OnlineError(f"--method {method!r}: online runs support {list(CERPE_METHODS)}")
    lconf, nconf = merge_conf(link_defaults, link_conf, "zenoh link conf"), dict(node_conf or {})
    zenoh_wire.check_chunk(lconf["team"], "--team")
    zenoh_session.zenoh_config({k: lconf[k] for k in zenoh_session.default_conf})  # bad options fail now
    ros.check_distro((nconf.get("ros") or {}).get("distro", ros.default_conf["distro"]))
    manifest = Path(manifest).resolve()
    if setting is None:
        with _machine_lock(manifest):
            setting = load_manifest_setting(manifest)
    enc = _encounter(setting, encounter, manifest)
    if robot not in enc.robot_ids:
        raise OnlineError(f"--robot {robot!r}: encounter {enc.name} of {manifest} has robots {enc.robot_ids}")
    out = Path(out)
    done = out / enc.name / DONE_JSON
    if done.exists() and not overwrite:
        raise RunError(f"{done}: this robot already finished encounter {enc.name}; "
                       f"use --overwrite to run it again (with its peers)")
    ensure_dir(write.check_out(out), "--out")  # before the link opens: an --out that cannot be written fails now
    link = ZenohLink(robot, enc.robot_ids, lconf)  # opens now: a bad endpoint fails before models load
    try:
        if plugins is None:
            plugins, config, mconf = cerpe_plugins_and_config(
                method, getattr(setting, "metric_depth", None), getattr(setting, "metric_depth_options", None),
                preset, dict(sets) if sets else None)
        else:
            config = config if config is not None else AlgorithmConfig()
            mconf = {"tree": config_dict(knobs.as_dict(config)), "preset": "given", "plugins": "given"}
        k = enc.robot_ids.index(robot)
        agent = RobotAgent(robot, k, config, plugins.descriptor, plugins.backbone, plugins.depth)
        node = RobotNode(agent, link, enc.robot_ids, conf=nconf)
    except BaseException:
        link.close(0.0)
        raise
    run_conf = {"method": method, "preset": preset, "seed": int(seed), "setting": setting.name,
                "encounters": [enc.name], "method_config": mconf, "code": code_hash(method),
                "online": {"robot": robot, "team": link.team, "robots": list(enc.robot_ids),
                           "link": config_dict(link.conf), "node": config_dict(node.conf)}}
    record = {"method": method, "label": METHOD_LABELS[method] + " (online)",
              "metric_scale": getattr(setting, "metric_depth", None) != "none", "manifest": str(manifest),
              "seed": int(seed), "preset": preset, "setting": setting.name, "zenoh_id": link.zid}
    try:
        folder = write.open_run(out, run_conf, record, overwrite=overwrite)
    except BaseException:
        link.close(0.0)
        raise
    with folder, node:
        stream = enc.robots[k]

        def frames() -> Iterator[tuple]:
            for t in range(enc.n_steps):
                yield stream.image(t), FrameContext(robot, t, stream.intrinsics, stream.depth_m(t), seed), \
                    float(stream.stamps_s[t])

        atomic_write_text(out / enc.name / PEER_OVERLAP_CSV, peers_overlap_csv(enc, robot))
        t0 = time.perf_counter()
        folder.write_encounter(enc, lambda _enc: node.run(frames()), progress=progress)
        report = {**node.report(), "wall_time_s": time.perf_counter() - t0}
        atomic_write_json(out / enc.name / "online.json", report)
        lost = {k: v for k, v in node.stats.items() if ":" in k}
        log.info("robot %s: %d steps, degradations %s", robot, report["n_steps"], lost or "none")
        if not node.met:
            log.warning("robot %s never met any of its peers %s (team %r): its run holds no inter-robot estimate; "
                        "check --team, the endpoints (--connect / --listen) and that the peers were started",
                        robot, list(node.peers), link.team)
    return OnlineRun(out, enc.name, sorted(node.met))


def peers_overlap_csv(enc: Any, robot: str) -> str:
    """``encounter, step, ego, other, overlap_gt`` of the pairs (peer, ``robot``): the overlap ground truth
    of the rows this robot's peers write about it, which its own success after co-visibility needs."""
    k = enc.robot_ids.index(robot)
    lines = ["encounter,step,ego,other,overlap_gt"]
    for j, peer in enumerate(enc.robot_ids):
        if j == k:
            continue
        for t in range(enc.n_steps):
            ov = float(enc.overlap[t, j, k]) if enc.overlap is not None else math.nan
            lines.append(f"{enc.name},{t},{peer},{robot},{'' if math.isnan(ov) else f'{ov:.9g}'}")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- CLI
def add_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("what to run")
    g.add_argument("--robot", required=True, help="this robot's id (a robot of the encounter, e.g. r0)")
    g.add_argument("--manifest", required=True, type=Path, help="dataset manifest (the same on every robot)")
    g.add_argument("--encounter", default=None,
                   help="encounter name in the manifest (may be left out when it has only one)")
    g.add_argument("--method", default="cerpe", choices=CERPE_METHODS,
                   help=" | ".join(CERPE_METHODS) + " (default %(default)s; the same on every robot)")
    g.add_argument("--preset", default="paper", metavar="P",
                   help="a named configuration (default: paper); `cerpe config show --presets` lists them")
    g.add_argument("--seed", type=int, default=0, help="random seed (the same on every robot)")
    g.add_argument("--rate", type=float, default=node_defaults["rate_hz"],
                   help="replay rate in frames/s (default 0: as fast as the team allows)")
    g.add_argument("--out", type=Path, default=None,
                   help="run folder (default build/online/<manifest name>/<method>/<robot>)")
    g.add_argument("--overwrite", action="store_true", help="run again although this robot's folder is finished")
    g.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="sets",
                   help="a knob of the configuration tree, as `cerpe run --set` (repeatable; the same on every "
                        "robot), e.g. messages.share_estimates=true")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")
    z = p.add_argument_group("network (Zenoh)")
    z.add_argument("--team", default=link_defaults["team"],
                   help="team name: robots talk only to robots of the same team (default %(default)s)")
    z.add_argument("--listen", action="append", default=[], metavar="EP",
                   help="Zenoh endpoint to listen on, repeatable, e.g. tcp/0.0.0.0:7447 "
                        "(default: any free port, announced by multicast scouting)")
    z.add_argument("--connect", action="append", default=[], metavar="EP",
                   help="Zenoh endpoint of a peer or router to dial, repeatable, e.g. tcp/10.0.0.1:7447")
    z.add_argument("--mode", default=link_defaults["mode"], choices=zenoh_session.MODES,
                   help="peer: robots talk directly (default); client: through the router given in --connect")
    z.add_argument("--no-multicast", action="store_true",
                   help="no UDP multicast scouting: find peers only through --connect/--listen")
    z.add_argument("--zenoh", action="append", default=[], metavar="PATH=VALUE",
                   help="any other Zenoh setting (json5 path of Zenoh's configuration, JSON value), repeatable, "
                        "e.g. transport/shared_memory/enabled=false")
    z.add_argument("--timeout", type=float, default=node_defaults["step_timeout_s"],
                   help="seconds to wait per phase for the peers' frames of the same step (default %(default)s)")
    z.add_argument("--connect-timeout", type=float, default=node_defaults["connect_timeout_s"],
                   help="seconds to wait for all peers before step 0 (default %(default)s)")
    z.add_argument("--linger", type=float, default=node_defaults["linger_s"],
                   help="after the last step, answer late image requests until every peer said bye, "
                        "at most this many seconds (default %(default)s)")
    r = p.add_argument_group("estimates out to ROS 2")
    r.add_argument("--ros-keys", default=node_defaults["ros"]["key_format"], choices=ROS_KEYS,
                   help="rmw_zenoh: rmw_zenoh's key (a ROS 2 graph on rmw_zenoh reads it); ros2dds: the key of "
                        "zenoh-bridge-ros2dds (a DDS graph through the bridge); off (default %(default)s)")
    r.add_argument("--ros-domain", type=int, default=node_defaults["ros"]["domain_id"],
                   help="ROS_DOMAIN_ID of the graph (rmw_zenoh keys; default %(default)s)")
    r.add_argument("--ros-distro", default=node_defaults["ros"]["distro"], choices=ros.DISTROS,
                   help="ROS 2 distribution of the graph that reads the estimates: humble (no type hash in the "
                        "key) or a later one (default %(default)s)")


def confs_from_args(args: argparse.Namespace) -> tuple[dict, dict]:
    """``(link_conf, node_conf)`` of the command-line options."""
    for name, v in (("--rate", args.rate), ("--timeout", args.timeout), ("--connect-timeout", args.connect_timeout),
                    ("--linger", args.linger)):
        if not v >= 0:
            raise OnlineError(f"{name} must be >= 0, got {v}")
    extra = {}
    for item in args.zenoh:
        path, eq, value = item.partition("=")
        if not eq or not path:
            raise OnlineError(f"--zenoh {item!r}: expected PATH=VALUE, e.g. transport/shared_memory/enabled=false")
        try:
            extra[path] = json.loads(value)
        except json.JSONDecodeError:
            extra[path] = value  # a bare string
    link = {"team": args.team, "mode": args.mode, "connect": list(args.connect), "listen": list(args.listen),
            "multicast_scouting": not args.no_multicast, "zenoh": extra or None}
    node = {"step_timeout_s": args.timeout, "connect_timeout_s": args.connect_timeout, "rate_hz": args.rate,
            "linger_s": args.linger,
            "ros": {"key_format": args.ros_keys, "domain_id": args.ros_domain, "distro": args.ros_distro}}
    return link, node


def main(args: argparse.Namespace) -> int:
    from ..pipeline.run import parse_sets

    link, node = confs_from_args(args)
    out = args.out
    if out is None:
        out = Path("build") / "online" / Path(args.manifest).stem / args.method / args.robot
    done = run_online(args.manifest, args.encounter, args.robot, out, link_conf=link, node_conf=node,
                      method=args.method, preset=args.preset, seed=args.seed, overwrite=args.overwrite,
                      progress=not args.no_progress, sets=parse_sets(args.sets) or None)
    print(f"run folder: {out}")
    if not done.peers_met:
        print(f"cerpe online: warning: robot {args.robot} never met any peer of its team {args.team!r}; "
              f"exit code {EXIT_NO_PEER}", file=sys.stderr)
        return EXIT_NO_PEER
    return 0
