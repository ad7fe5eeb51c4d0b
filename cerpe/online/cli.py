"""Run ONE robot of a team online: this process talks to its peers over Zenoh.

On a robot, reading its own ROS 2 topics (each robot in its namespace, e.g. /r0):

    cerpe online --robot r0 --robots r0,r1 --team lab --input ros --depth-topic camera/depth/image_raw

Replaying a dataset, one process per robot (the same manifest, encounter and --team on every one):

    cerpe online --robot r0 --manifest datasets_manifest/synthetic-indoor.yaml --encounter indoor-s0-e00

What it does: runs Algorithm 1 for this robot with its peers, each at its own pace, by capture
stamps. It takes its newest camera frame whenever it is ready (frames it could not keep up with
are dropped and counted), publishes the frame's descriptor and odometry pose with their stamp on
cerpe/<team>/<robot>/{descriptor,pose}, scores each peer's descriptor nearest its own stamp, asks
a peer for an image by that frame's stamp (a Zenoh query to cerpe/<team>/<peer>/image), and reads
each peer's pose at its own stamp from the peer's pose stream (interpolated; extrapolated at most
stamps.max_extrapolation_s, else counted). Robots start in any order, join late, leave and come
back; nobody waits for a full team. --lockstep instead runs a manifest's team in lock-step rounds,
which reproduces `cerpe run` exactly (every robot waits for its peers' frames of each step).

Input: --input ros reads sensor_msgs/Image or CompressedImage (rgb8, bgr8, mono8), its CameraInfo,
an optional aligned depth Image (16UC1 mm, 32FC1 m) and optional odometry (nav_msgs/Odometry, or TF
odom -> base_link with the camera's extrinsic from /tf_static or --camera-extrinsic), in the key
layout of rmw_zenoh or of zenoh-bridge-ros2dds (--input-keys). No ROS installation is needed. A
bag plays these topics with `cerpe bag play`. --input manifest replays the manifest's frames at
--speed times real time. With --input ros a manifest is optional: it then names the roster and the
ground truth (matched by stamp, for `cerpe eval`).

Finding the peers: by default Zenoh peer mode with UDP multicast scouting (224.0.0.224:7446) on the
LAN. Where multicast does not pass (Wi-Fi, VPN, another subnet), let one robot listen on a fixed
endpoint, --listen tcp/0.0.0.0:7447, and give the others --connect tcp/<its IP>:7447. With a Zenoh
router (zenohd, or ROS 2's rmw_zenohd: what --input ros with rmw_zenoh reads through), --connect
tcp/<router>:7447 (--mode client for a client). Firewall: the TCP port of --listen and UDP 7446.
Robots of another --team or cerpe version, or the other sync mode, are named in a warning and
counted, never mixed in. Clocks: a peer's stamps off this robot's clock by more than
--clock-tolerance are mapped by the offset estimated from message arrival (counted once).

Out: every frame's estimate of each peer T_cj_ci (this robot's camera in the peer's, optical axes,
metres) as a geometry_msgs/msg/PoseWithCovarianceStamped on /cerpe/<team>/<robot>/relative_pose/<peer>
(stamp: the frame's capture time; covariance: the pose graph's, or the switch's propagation model's;
frames without an estimate publish nothing), optionally TF (--tf), and the newest one on the Zenoh
queryable cerpe/<team>/<robot>/latest/<peer> for a controller that polls. Keys: --ros-keys rmw_zenoh
(a ROS 2 graph on rmw_zenoh reads it), ros2dds (through zenoh-bridge-ros2dds), off. --team and robot
ids must then be ROS name tokens (a letter, then letters, digits, '_').

Run folder (cerpe.runfolder) with only this robot as ego, plus <encounter>/online.json (link
counters, per-frame times, latency from an image's arrival to its estimates published, peer
events, dropped frames) and, with a manifest, peers_overlap.csv. `cerpe eval` reads it; the folders
of a team together evaluate the team. Ctrl-C ends the run after the frame in progress (its folder is
written) and the robot says bye; its peers name it.

Exit status: 0 when the run finished having met at least one peer; 4 when it finished without ever
meeting any peer (a warning says so); 2 for a bad option, an unknown robot or encounter, an --out that
cannot be written, or a Zenoh session that cannot open: one line on stderr.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..methods import CERPE_METHODS
from . import ros, zenoh_session
from .node import ROS_KEYS, OnlineError
from .node import default_conf as node_defaults
from .ros_input import default_conf as input_defaults
from .run import INPUTS, OnlineRun, peers_overlap_csv, run_online
from .zenoh_link import default_conf as link_defaults

__all__ = ["EXIT_NO_PEER", "OnlineRun", "add_arguments", "confs_from_args", "main", "peers_overlap_csv", "run_online"]

EXIT_NO_PEER = 4  # the run finished without ever meeting any peer (see the module doc)


def add_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("what to run")
    g.add_argument("--robot", required=True, help="this robot's id (a robot of the roster, e.g. r0)")
    g.add_argument("--input", default="manifest", choices=INPUTS,
                   help="ros: this robot's ROS 2 topics (below); manifest: replay its frames of --manifest "
                        "(default %(default)s)")
    g.add_argument("--manifest", type=Path, default=None,
                   help="dataset manifest (the same on every robot); with --input ros optional: the roster and "
                        "ground truth")
    g.add_argument("--encounter", default=None,
                   help="encounter name in the manifest (may be left out when it has only one)")
    g.add_argument("--robots", default=None, metavar="IDS",
                   help="the team's roster, comma separated, the same order on every robot (--input ros without "
                        "a manifest)")
    g.add_argument("--method", default="cerpe", choices=CERPE_METHODS,
                   help=" | ".join(CERPE_METHODS) + " (default %(default)s; the same on every robot)")
    g.add_argument("--preset", default="paper", metavar="P",
                   help="a named configuration (default: paper); `cerpe config show --presets` lists them")
    g.add_argument("--seed", type=int, default=0, help="random seed (the same on every robot)")
    g.add_argument("--speed", type=float, default=1.0,
                   help="replay speed against the manifest's stamps: 1 real time, 2 twice as fast, 0 every frame "
                        "as fast as this robot computes (default %(default)s)")
    g.add_argument("--lockstep", action="store_true",
                   help="replay the manifest's team in lock-step rounds (every robot waits for its peers' frames "
                        "of each step): reproduces `cerpe run` exactly; on every robot or none")
    g.add_argument("--registration", choices=("worker", "inline"), default="worker",
                   help="worker (default): a peer's received image is registered on a worker thread and its "
                        "estimate lands when ready, carried to the newest frame with both robots' odometry, so "
                        "the robot keeps its pace; inline: in the frame's step (--lockstep always registers inline)")
    g.add_argument("--rate", type=float, default=node_defaults["rate_hz"],
                   help="--lockstep: replay rate in steps/s (default 0: as fast as the team allows)")
    g.add_argument("--use-odometry", action="store_true",
                   help="replay: the manifest's odometry (rosbag adapter, odometry_topic) as the robot's ego-motion")
    g.add_argument("--stall", type=float, default=input_defaults["stall_s"], metavar="S",
                   help="a gap between camera frames longer than S seconds is counted (input:stall; 0: never; "
                        "default %(default)s)")
    g.add_argument("--out", type=Path, default=None,
                   help="run folder (default build/online/<manifest name or live>/<method>/<robot>)")
    g.add_argument("--overwrite", action="store_true", help="run again although this robot's folder is finished")
    g.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="sets",
                   help="a knob of the configuration tree, as `cerpe run --set` (repeatable; the same on every "
                        "robot), e.g. stamps.max_extrapolation_s=0.3")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")
    i = p.add_argument_group("input from ROS 2 topics (--input ros)")
    i.add_argument("--ros-namespace", default=None, metavar="NS",
                   help="relative topic names resolve here (default /<robot>)")
    i.add_argument("--image-topic", default=input_defaults["image_topic"],
                   help="sensor_msgs/Image or CompressedImage (default %(default)s)")
    i.add_argument("--camera-info-topic", default=None, help="its CameraInfo (default: camera_info beside the image)")
    i.add_argument("--depth-topic", default=None, help="aligned depth Image, 16UC1 mm or 32FC1 m (default: none)")
    i.add_argument("--odom-topic", default=None, help="nav_msgs/Odometry of the robot (default: none: the camera's "
                                                      "own ego-motion)")
    i.add_argument("--tf-odometry", action="store_true",
                   help="the robot's odometry from TF --odom-frame -> --base-frame on /tf")
    i.add_argument("--odom-frame", default=input_defaults["odom_frame"], help="(default %(default)s)")
    i.add_argument("--base-frame", default=input_defaults["base_frame"], help="(default %(default)s)")
    i.add_argument("--camera-extrinsic", default=None, metavar="'X Y Z QX QY QZ QW'",
                   help="the camera's optical frame in the base frame (default: from /tf_static)")
    i.add_argument("--input-keys", default=None, choices=ros.KEY_FORMATS,
                   help="how the topics reach Zenoh: rmw_zenoh or ros2dds (default: as --ros-keys)")
    i.add_argument("--depth-tolerance", type=float, default=input_defaults["depth_tolerance_s"], metavar="S",
                   help="an image's depth: the nearest depth message within S seconds (default %(default)s)")
    i.add_argument("--idle-exit", type=float, default=input_defaults["idle_exit_s"], metavar="S",
                   help="end the run when no image came for S seconds (default 0: never; Ctrl-C ends it)")
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
    z.add_argument("--timeout", type=float, default=None,
                   help="longest wait for a peer's frame: by stamps a descriptor, reply or pose near this frame's "
                        f"stamp (default {node_defaults['wait_s']} s); --lockstep the peers' frames of the same step "
                        f"(default {node_defaults['step_timeout_s']} s)")
    z.add_argument("--reply-timeout", type=float, default=node_defaults["reply_timeout_s"], metavar="S",
                   help="by stamps: longest wait for a peer's reply to an image request (default %(default)s)")
    z.add_argument("--connect-timeout", type=float, default=node_defaults["connect_timeout_s"],
                   help="replays: seconds to wait for all peers before the first frame (default %(default)s)")
    z.add_argument("--linger", type=float, default=node_defaults["linger_s"],
                   help="after the last frame, answer late image requests until every peer said bye, "
                        "at most this many seconds (default %(default)s)")
    z.add_argument("--clock-tolerance", type=float, default=link_defaults["clock_tolerance_s"], metavar="S",
                   help="--input ros: a peer whose clock is off this robot's by more than S seconds has its stamps "
                        "mapped (default %(default)s; a replay's stamps are the dataset's, never mapped)")
    r = p.add_argument_group("estimates out to ROS 2")
    r.add_argument("--ros-keys", default=node_defaults["ros"]["key_format"], choices=ROS_KEYS,
                   help="rmw_zenoh: rmw_zenoh's key (a ROS 2 graph on rmw_zenoh reads it); ros2dds: the key of "
                        "zenoh-bridge-ros2dds (a DDS graph through the bridge); off (default %(default)s)")
    r.add_argument("--ros-domain", type=int, default=node_defaults["ros"]["domain_id"],
                   help="ROS_DOMAIN_ID of the graph (rmw_zenoh keys; default %(default)s)")
    r.add_argument("--ros-distro", default=node_defaults["ros"]["distro"], choices=ros.DISTROS,
                   help="ROS 2 distribution of the graph: humble (no type hash in the key) or a later one "
                        "(default %(default)s)")
    r.add_argument("--tf", action="store_true",
                   help="also publish the estimates as TF: each peer's camera <team>/<robot>/peers/<peer>/"
                        "camera_optical under this robot's <team>/<robot>/camera_optical")


def confs_from_args(args: argparse.Namespace) -> tuple[dict, dict, dict]:
    """``(link_conf, node_conf, ros_input_conf)`` of the command-line options."""
    for name, v in (("--rate", args.rate), ("--timeout", 0.0 if args.timeout is None else args.timeout),
                    ("--connect-timeout", args.connect_timeout), ("--linger", args.linger),
                    ("--reply-timeout", args.reply_timeout),
                    ("--clock-tolerance", args.clock_tolerance), ("--stall", args.stall),
                    ("--depth-tolerance", args.depth_tolerance), ("--idle-exit", args.idle_exit)):
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
            "multicast_scouting": not args.no_multicast, "zenoh": extra or None,
            "sync": "lockstep" if args.lockstep else "stamps", "clock_tolerance_s": args.clock_tolerance}
    node = {"connect_timeout_s": args.connect_timeout, "rate_hz": args.rate, "linger_s": args.linger, "tf": args.tf,
            "reply_timeout_s": args.reply_timeout,
            "ros": {"key_format": args.ros_keys, "domain_id": args.ros_domain, "distro": args.ros_distro}}
    if args.timeout is not None:
        node["step_timeout_s" if args.lockstep else "wait_s"] = args.timeout
    keys = args.input_keys or (args.ros_keys if args.ros_keys != "off" else "rmw_zenoh")
    inp = {"namespace": args.ros_namespace, "image_topic": args.image_topic, "camera_info_topic": args.camera_info_topic,
           "depth_topic": args.depth_topic, "odom_topic": args.odom_topic, "tf_odometry": args.tf_odometry,
           "odom_frame": args.odom_frame, "base_frame": args.base_frame, "camera_extrinsic": args.camera_extrinsic,
           "key_format": keys, "domain_id": args.ros_domain, "depth_tolerance_s": args.depth_tolerance,
           "stall_s": args.stall, "idle_exit_s": args.idle_exit}
    return link, node, inp


def main(args: argparse.Namespace) -> int:
    from ..pipeline.run import parse_sets

    link, node, inp = confs_from_args(args)
    robots = [r.strip() for r in args.robots.split(",") if r.strip()] if args.robots else None
    out = args.out
    if out is None:
        out = Path("build") / "online" / (Path(args.manifest).stem if args.manifest else "live") / args.method / args.robot
    done = run_online(args.manifest, args.encounter, args.robot, out, link_conf=link, node_conf=node,
                      method=args.method, preset=args.preset, seed=args.seed, overwrite=args.overwrite,
                      progress=not args.no_progress, sets=parse_sets(args.sets) or None, input=args.input,
                      robots=robots, speed=args.speed, use_odometry=args.use_odometry, ros_input=inp,
                      stall_s=args.stall, registration=args.registration)
    print(f"run folder: {out}")
    if not done.peers_met:
        print(f"cerpe online: warning: robot {args.robot} never met any peer of its team {args.team!r}; "
              f"exit code {EXIT_NO_PEER}", file=sys.stderr)
        return EXIT_NO_PEER
    return 0
