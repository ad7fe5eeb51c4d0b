"""A robot's ROS 2 topics as its frames (cerpe.online.ros_input), its estimates out, and bad input on the command line.

* Both key layouts (rmw_zenoh, zenoh-bridge-ros2dds): a publisher on loopback sends what a robot's
  graph would, one message at a time, including every bad message of the issue: an unsupported
  encoding, a CameraInfo of zeros, a depth image of another size, odometry with NaN, a message of
  the wrong type on the image topic, an image older than the last, an image without its depth.
  Each is counted once (and the frame after carries it); the good frames come out with the right
  pixels, intrinsics, depth and ``T_odom_cam``; nothing raises.
* Two robots by stamps through ``run_online`` (test doubles): each estimate goes out with the
  covariance its record carries, as TF, and the newest on the queryable.
* ``cerpe online`` and ``cerpe bag`` refuse bad options and bags with one line, exit code 2.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

zenoh = pytest.importorskip("zenoh")

from cerpe.geometry import make_se3, se3_from_tq_xyzw  # noqa: E402
from cerpe.online import ros  # noqa: E402
from cerpe.online import zenoh_wire as w  # noqa: E402
from cerpe.online.ros_input import RosInput  # noqa: E402
from cerpe.online.run import run_online  # noqa: E402
from cerpe.rosio import encode  # noqa: E402
from cerpe.rosio import types as rt  # noqa: E402
from cerpe.scene import CameraIntrinsics, Setting  # noqa: E402
from gt_backbone import GTBackbone, OverlapDescriptor, SensorDepthDouble, make_world  # noqa: E402
from test_online import _raw_conf, link_confs, run_threads  # noqa: E402
from test_online_zenoh_link import endpoint, free_ports  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
K = CameraIntrinsics(40.0, 40.0, 15.5, 11.5, 32, 24)
RGB = np.random.default_rng(0).integers(0, 255, (24, 32, 3), dtype=np.uint8)
EXTRINSIC = se3_from_tq_xyzw([0.1, 0.0, 0.2], [-0.5, 0.5, -0.5, 0.5])  # a camera looking along the base's x


def sessions():
    (port,) = free_ports(1)
    return zenoh.open(_raw_conf([], [endpoint(port)])), zenoh.open(_raw_conf([endpoint(port)], []))


@pytest.mark.parametrize("key_format", ros.KEY_FORMATS)
def test_topics_in_both_layouts_and_every_bad_message_counted(key_format):
    conf = {"key_format": key_format, "domain_id": 0, "distro": "jazzy"}
    sub, pub = sessions()
    src = RosInput(sub, "r0", {"key_format": key_format, "depth_topic": "camera/depth", "odom_topic": "odom",
                               "camera_extrinsic": "0.1 0 0.2 -0.5 0.5 -0.5 0.5"})
    got: list = []
    th = threading.Thread(target=lambda: got.extend(src.frames()), daemon=True)

    def put(topic, kind, msg, as_kind=None):
        """``msg`` on ``topic``; ``as_kind``: the type the key names (rmw_zenoh), when not ``kind``."""
        pub.put(ros.zenoh_key(topic, conf, as_kind or kind), rt.serialize(msg, kind),
                attachment=ros.rmw_attachment(1, time.time_ns(), bytes(16)) if key_format == "rmw_zenoh" else None)
        time.sleep(0.4)  # one message at a time: the robot takes each image before the next comes

    img, info, depth, odom = "/r0/camera/image_raw", "/r0/camera/camera_info", "/r0/camera/depth", "/r0/odom"
    time.sleep(0.5)  # the subscriptions reach the publisher
    th.start()
    try:
        put(img, rt.IMAGE, encode.image(RGB, 1.0, "cam"))                          # before any CameraInfo
        zeros = encode.camera_info(K, 1.0, "cam")
        zeros.k = np.zeros(9)
        put(info, rt.CAMERA_INFO, zeros)                                           # a CameraInfo of zeros
        put(info, rt.CAMERA_INFO, encode.camera_info(K, 1.0, "cam"))
        d = np.full((24, 32), 2.0)
        put(depth, rt.IMAGE, encode.depth(d, 2.0, "cam"))
        put(img, rt.IMAGE, encode.image(RGB, 2.0, "cam"))                          # good, with depth
        bad = encode.image(RGB, 3.0, "cam")
        bad.encoding = "yuv422"
        put(img, rt.IMAGE, bad)                                                    # an unsupported encoding
        put(depth, rt.IMAGE, encode.depth(np.ones((12, 16)), 4.0, "cam"))
        put(img, rt.IMAGE, encode.image(RGB, 4.0, "cam", "bgr8"))                  # depth of another size
        put(img, rt.CAMERA_INFO, encode.camera_info(K, 4.5, "cam"), as_kind=rt.CAMERA_INFO if key_format ==
            "rmw_zenoh" else None)                                                 # the wrong type on the topic
        nan = encode.odometry(np.eye(4), 4.8)
        nan.pose.pose.position.x = float("nan")
        put(odom, rt.ODOMETRY, nan)                                                # odometry with NaN
        for s, x in ((4.9, 1.0), (5.1, 3.0)):
            put(odom, rt.ODOMETRY, encode.odometry(make_se3(np.eye(3), [x, 0, 0]), s))
        put(depth, rt.IMAGE, encode.depth(d, 5.0, "cam"))
        put(img, rt.IMAGE, encode.image(RGB, 5.0, "cam", "mono8"))                 # good, odometry interpolated
        put(img, rt.IMAGE, encode.image(RGB, 4.7, "cam"))                          # older than the last taken
        put(img, rt.IMAGE, encode.image(RGB, 6.0, "cam"))                          # no depth message for it
        time.sleep(0.5)
        src.stop()
        th.join(10)
    finally:
        src.stop()
        src.close()
        sub.close()
        pub.close()
    assert not th.is_alive()
    assert [f.stamp_s for f in got] == [2.0, 4.0, 5.0, 6.0]
    assert np.array_equal(got[0].image, RGB) and np.array_equal(got[1].image, RGB)
    assert got[0].context.intrinsics == K and np.allclose(got[0].context.sensor_depth_m, 2.0, atol=1e-3)
    assert got[1].context.sensor_depth_m is None and got[3].context.sensor_depth_m is None
    np.testing.assert_allclose(got[2].T_odom_cam, make_se3(np.eye(3), [2.0, 0, 0]) @ EXTRINSIC, atol=1e-9)
    counted = [d for f in got for d in f.degradations]
    for what in ("input:no-camera-info", "input:bad-camera-info", "input:bad-image", "input:bad-depth",
                 "input:wrong-type", "input:bad-odometry", "input:out-of-order", "input:no-depth"):
        assert counted.count(what) == 1, (what, counted)
        assert src.stats[what] == 1 or what == "input:no-depth", (what, dict(src.stats))


def test_estimates_out_with_their_covariance_as_tf_and_on_the_queryable(tmp_path):
    world = make_world(2, 8, seed=8, windows={(0, 1): [(1, 6)]})
    setting = Setting("toy-stamps", [world.to_encounter("enc")])
    confs = link_confs(world.robot_ids, team="lab")
    (port,) = free_ports(1)
    for c in confs.values():
        c["connect"].append(endpoint(port))
        c["sync"] = "stamps"
    listener = zenoh.open(_raw_conf([], [endpoint(port)]))
    got, tfs = [], []
    subs = [listener.declare_subscriber("0/cerpe/lab/**", lambda s: got.append((str(s.key_expr), s.payload.to_bytes()))),
            listener.declare_subscriber("0/tf/**", lambda s: tfs.append(s.payload.to_bytes()))]
    latest = {}

    def job(rid):
        plugins = type("P", (), {"descriptor": OverlapDescriptor(world), "backbone": GTBackbone(world, seed=1),
                                 "depth": SensorDepthDouble()})
        node_conf = {"linger_s": 1.0, "tf": True, "ros": {"key_format": "rmw_zenoh"}}
        from test_online import CFG

        def run():
            out = run_online(tmp_path / "m.yaml", None, rid, tmp_path / rid, link_conf=confs[rid], node_conf=node_conf,
                             setting=setting, plugins=plugins, config=CFG, progress=False, speed=0.0)
            return out
        return run

    def poll():  # a controller polling r0's newest estimate of r1 while the robots run
        for _ in range(60):
            for r in listener.get(w.latest_key("lab", "r0", "r1"), timeout=1.0):
                if r.ok is not None:
                    latest["r1"] = r.ok.payload.to_bytes()
            time.sleep(0.05)

    try:
        run_threads({"r0": job("r0"), "r1": job("r1"), "poll": poll})
        time.sleep(0.3)
    finally:
        for s in subs:
            s.undeclare()
        listener.close()
    steps = pd.read_csv(tmp_path / "r0" / "enc" / "steps.csv")
    est = steps[steps.source != "none"]
    assert len(est) >= 3 and est["sigma_rot_rad"].gt(0).all() and est["sigma_pos_m"].gt(0).all()
    key = ros.zenoh_key(ros.topic_name("lab", "r0", "r1"), ros.default_conf)
    mine = [ros.decode_pose_cdr(p) for k, p in got if k == key]
    assert len(mine) == len(est)
    for msg, (_, row) in zip(mine, est.iterrows()):
        sig_rot = np.sqrt(np.trace(msg["covariance"][3:, 3:]))  # ROS order: rotation last
        assert msg["stamp_s"] == pytest.approx(row["stamp_s"]) and sig_rot == pytest.approx(row["sigma_rot_rad"])
    assert ros.decode_pose_cdr(latest["r1"])["stamp_s"] <= mine[-1]["stamp_s"]
    frames = {(t.header.frame_id, t.child_frame_id) for cdr in tfs
              for t in rt.deserialize(cdr, rt.TF_MESSAGE, "/tf").transforms}
    assert ("lab/r0/camera_optical", "lab/r0/peers/r1/camera_optical") in frames
    rep = json.loads((tmp_path / "r0" / "enc" / "online.json").read_text())
    assert rep["sync"] == "stamps" and rep["peers_met"] == ["r1"] and rep["n_steps"] > 0


def _cli(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.run([sys.executable, "-m", "cerpe.cli", *args], capture_output=True, text=True, timeout=120,
                          env=env)


def test_bad_options_and_bags_are_one_line(tmp_path):
    from cerpe.rosio.bags import write_bag

    bag = write_bag(tmp_path / "b", [("/r0/camera/image_raw", rt.IMAGE, 10**9, encode.image(RGB, 1.0, "cam"))], "mcap")
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(next(bag.glob("*.mcap")).read_bytes()[:3000])
    online = ["online", "--robot", "r0", "--no-multicast", "--ros-keys", "off"]
    for args, match in [(online + ["--input", "ros"], "--input ros needs the team's roster"),
                        (online + ["--input", "ros", "--robots", "r0,r1", "--camera-extrinsic", "1 2"],
                         "--camera-extrinsic '1 2': expected 7 numbers"),
                        (online + ["--input", "ros", "--robots", "r0,r1", "--lockstep"], "--lockstep replays a manifest"),
                        (online + ["--input", "ros", "--robots", "r0,r1", "--image-topic", "a b"], "not a ROS topic name"),
                        (online + ["--input", "ros", "--robots", "r0,r1", "--stall", "-1"], "--stall must be >= 0"),
                        (online + ["--input", "ros", "--robots", "r0,r1", "--set", "messages.share_estimates=true",
                                   "--out", str(tmp_path / "o")], "share_estimates needs the robots in lock-step"),
                        (["bag", "play", str(bag), "--robot", "r0", "--no-multicast", "--topics", "/nope"],
                         "--topics /nope: not in the bag; it holds /r0/camera/image_raw"),
                        (["bag", "play", str(cut), "--robot", "r0", "--no-multicast"], "does not open as a ROS bag"),
                        (["bag", "info", str(tmp_path / "none.mcap")], "bag not found")]:
        proc = _cli(*args)
        assert proc.returncode == 2, (args, proc.stderr)
        assert "Traceback" not in proc.stderr and match in proc.stderr, (args, proc.stderr)
