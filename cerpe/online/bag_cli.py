"""ROS bags for cerpe: play one on Zenoh as a robot's topics, write a dataset as bags, list a bag.

    cerpe bag write datasets_manifest/dev-tum-fr1-xyz.yaml --out build/bags
    cerpe bag play build/bags/fwd --robot fwd            # in one terminal per robot ...
    cerpe online --robot fwd --robots fwd,rev --input ros --depth-topic camera/depth/image_raw
    cerpe bag info build/bags/fwd

play: publishes the bag's topics on Zenoh at their recorded times (--rate 0.5: half speed), on the
keys of rmw_zenoh (default) or zenoh-bridge-ros2dds, so `cerpe online --input ros` (and any ROS 2
node on rmw_zenoh) reads them as a live robot's. For --robot ID: a bag with topics under /ID/ plays
those; any other bag plays all its topics under the namespace /ID (--namespace overrides; / keeps
them as they are). Bags: ROS 1 .bag, ROS 2 folders, .db3 or .mcap files. Peers are found as by
`cerpe online` (multicast scouting, or --connect / --listen).

write: the encounters of a manifest (as its adapter loads them) as one ROS 2 bag per robot
(/<robot>/camera/image_raw, camera_info, depth/image_raw, ground_truth/pose) and the `rosbag`
manifest that reads them, so `cerpe run` and `cerpe online --input ros` run on the same data.

Bad input (a bag that does not open or is cut short, a topic it does not hold, a bad option): one
line on stderr, exit code 2.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from ..errors import CerpeError
from . import ros, zenoh_session


class BagCliError(CerpeError, ValueError):
    pass


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="bag_command", metavar="play|write|info", required=True)
    play = sub.add_parser("play", help="publish a bag's topics on Zenoh in real time, as a robot's ROS 2 graph")
    play.add_argument("bag", type=Path, help="a ROS 1 .bag, a ROS 2 bag folder, a .db3 or an .mcap")
    play.add_argument("--robot", required=True, help="the robot whose topics these are (its namespace /ID)")
    play.add_argument("--rate", type=float, default=1.0, help="playback speed (default 1: real time)")
    play.add_argument("--namespace", default=None, help="publish under this namespace (default /<robot>; / as is)")
    play.add_argument("--topics", nargs="+", default=None, metavar="TOPIC", help="only these topics of the bag")
    play.add_argument("--start-at", type=float, default=None, metavar="EPOCH",
                      help="wall time (s since the epoch) of the first message, to start several players together")
    play.add_argument("--ros-keys", default="rmw_zenoh", choices=ros.KEY_FORMATS,
                      help="rmw_zenoh (default) or ros2dds: the key layout the topics go out in")
    play.add_argument("--ros-domain", type=int, default=0, help="ROS_DOMAIN_ID (rmw_zenoh keys; default 0)")
    play.add_argument("--ros-distro", default="jazzy", choices=ros.DISTROS, help="(default jazzy)")
    play.add_argument("--listen", action="append", default=[], metavar="EP", help="Zenoh endpoint to listen on")
    play.add_argument("--connect", action="append", default=[], metavar="EP", help="Zenoh endpoint to dial")
    play.add_argument("--mode", default="peer", choices=zenoh_session.MODES, help="(default peer)")
    play.add_argument("--no-multicast", action="store_true", help="no UDP multicast scouting")
    write = sub.add_parser("write", help="write a manifest's encounters as ROS 2 bags, one per robot")
    write.add_argument("manifest", type=Path)
    write.add_argument("--out", type=Path, required=True, help="folder of the bags and their manifest")
    write.add_argument("--encounter", default=None, help="only this encounter (default: every one)")
    write.add_argument("--storage", default="mcap", choices=("mcap", "sqlite3", "ros1"), help="(default mcap)")
    write.add_argument("--image-format", default="raw", choices=("raw", "jpeg", "png"),
                       help="raw: sensor_msgs/Image rgb8 (default); jpeg, png: CompressedImage")
    write.add_argument("--depth-encoding", default="16UC1", choices=("16UC1", "32FC1"), help="(default 16UC1, mm)")
    write.add_argument("--frame-rate", type=float, default=None, metavar="HZ",
                       help="re-time the frames to HZ frames per second, every robot alike (default: their stamps; "
                            "e.g. to play a short 30 Hz sequence to robots that process 1 frame/s)")
    info = sub.add_parser("info", help="a bag's topics, types, message counts and duration")
    info.add_argument("bag", type=Path)


def main(args: argparse.Namespace) -> int:
    return {"play": _play, "write": _write, "info": _info}[args.bag_command](args)


def _play(args: argparse.Namespace) -> int:
    from .bag_play import play

    ros_conf = {"key_format": args.ros_keys, "domain_id": args.ros_domain, "distro": ros.check_distro(args.ros_distro)}
    conf = {**zenoh_session.default_conf, "mode": args.mode, "connect": list(args.connect),
            "listen": list(args.listen), "multicast_scouting": not args.no_multicast}
    session = zenoh_session.open_session(conf, f"bag player of {args.robot}")
    try:
        counts = play(args.bag, args.robot, session, ros_conf, args.rate, args.namespace, args.topics, args.start_at)
        time.sleep(0.2)  # the last samples leave before the session closes
    finally:
        session.close()
    print(json.dumps({"played": counts}))
    return 0


def _write(args: argparse.Namespace) -> int:
    from ..datasets import load_setting
    from ..datasets.bag_write import write_encounter

    setting = load_setting(args.manifest)
    encs = [e for e in setting.encounters if args.encounter in (None, e.name)]
    if not encs:
        raise BagCliError(f"--encounter {args.encounter!r}: {args.manifest} has {[e.name for e in setting.encounters]}")
    for enc in encs:
        out = args.out if len(encs) == 1 else args.out / enc.name
        if args.frame_rate is not None and not args.frame_rate > 0:
            raise BagCliError(f"--frame-rate must be > 0, got {args.frame_rate}")
        bags, manifest = write_encounter(enc, out, args.storage, args.image_format, args.depth_encoding,
                                         frame_rate=args.frame_rate)
        print(f"{enc.name}: {', '.join(f'{r} -> {p}' for r, p in bags.items())}; manifest {manifest}")
    return 0


def _info(args: argparse.Namespace) -> int:
    from ..rosio.bags import BagReader

    with BagReader(args.bag) as bag:
        counts = bag.counts
        print(f"{args.bag}: {'ROS 1' if bag.ros1 else 'ROS 2'} bag, {bag.duration_s:.3f} s")
        for topic, kind in sorted(bag.topics.items()):
            print(f"  {topic}  {kind}  {counts.get(topic, 0)} messages")
    return 0
