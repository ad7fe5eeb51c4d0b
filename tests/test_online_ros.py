"""Estimates out to ROS 2: CDR PoseWithCovarianceStamped round trips (rosbags deserializer) and the
Zenoh keys/attachments a ROS 2 graph reads through rmw_zenoh or zenoh-bridge-ros2dds."""
from __future__ import annotations

import json
import socket
import threading

import numpy as np
import pytest

from cerpe.geometry import paper_T_ij, random_se3, se3_inverse
from cerpe.online import ros
from cerpe.online.publish import EstimatePublisher
from cerpe.records import PairRecord


@pytest.mark.parametrize("seed", range(20))
def test_decoded_pose_with_covariance_equals_the_estimate(seed):
    rng = np.random.default_rng(seed)
    X_i, X_j = random_se3(rng, 20.0), random_se3(rng, 20.0)
    T_cj_ci = paper_T_ij(X_i, X_j)
    A = rng.standard_normal((6, 6))
    cov = A @ A.T if seed % 2 else None
    stamp = float(rng.uniform(0, 2e9))
    got = ros.decode_pose_cdr(ros.encode_pose_cdr(T_cj_ci, stamp, "lab/r1/camera_optical", cov))
    np.testing.assert_allclose(got["T_cj_ci"], T_cj_ci, atol=1e-12)
    # the pose is camera i's in camera j: it maps camera-i points into camera j
    p_ci = rng.standard_normal(3)
    p_w = X_i[:3, :3] @ p_ci + X_i[:3, 3]
    np.testing.assert_allclose(got["T_cj_ci"][:3, :3] @ p_ci + got["T_cj_ci"][:3, 3],
                               (se3_inverse(X_j) @ np.append(p_w, 1.0))[:3], atol=1e-9)
    assert got["frame_id"] == "lab/r1/camera_optical"
    assert abs(got["stamp_s"] - stamp) < 1e-6
    np.testing.assert_array_equal(got["covariance"], np.zeros((6, 6)) if cov is None else cov)


def test_cdr_bytes_are_ros2_cdr_little_endian():
    cdr = ros.encode_pose_cdr(np.eye(4), 12.5, "t/r1/camera_optical")
    assert cdr[:4] == b"\x00\x01\x00\x00"  # CDR_LE encapsulation
    # header.stamp (sec=12, nanosec=500000000) then the frame id string with its NUL
    assert cdr[4:12] == (12).to_bytes(4, "little") + (500_000_000).to_bytes(4, "little")
    assert cdr[12:16] == (20).to_bytes(4, "little") and cdr[16:36] == b"t/r1/camera_optical\x00"


@pytest.mark.parametrize("bad, match", [
    (np.diag([1, 1, 1, 1, 1, 1.0]) + np.eye(6, k=1), "symmetric"),
    (-np.eye(6), "negative variance"),
    (np.eye(3), "6x6"),
])
def test_bad_covariance_is_refused(bad, match):
    with pytest.raises(ros.RosError, match=match):
        ros.encode_pose_cdr(np.eye(4), 0.0, "f", bad)


def test_bad_pose_stamp_and_names_are_refused():
    with pytest.raises(ros.RosError, match="T_cj_ci"):
        ros.encode_pose_cdr(np.full((4, 4), np.nan), 0.0, "f")
    with pytest.raises(ros.RosError, match="stamp"):
        ros.encode_pose_cdr(np.eye(4), -1.0, "f")
    with pytest.raises(ros.RosError, match="--team 'lab-a'"):
        ros.topic_name("lab-a", "r0", "r1")
    with pytest.raises(ros.RosError, match="not a CDR"):
        ros.decode_pose_cdr(b"\x00\x01\x00\x00\x01")


def test_keys_follow_rmw_zenoh_and_the_dds_bridge():
    topic = ros.topic_name("lab", "r0", "r1")
    assert topic == "/cerpe/lab/r0/relative_pose/r1"
    key = ros.zenoh_key(topic, ros.default_conf)
    assert key == ("0/cerpe/lab/r0/relative_pose/r1/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/"
                   "RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e")
    # the hash is REP 2016's: rosbags gives std_msgs/String the value rmw_zenoh's design doc shows
    from rosbags.typesys import Stores, get_typestore
    assert get_typestore(Stores.ROS2_JAZZY).hash_rihs01("std_msgs/msg/String").endswith("df668c740482bbd48fb3"
                                                                                        "9d76a70dfd4bd59db1288021743503259e948f6b1a18")
    assert ros.zenoh_key(topic, {**ros.default_conf, "distro": "humble", "domain_id": 7}).startswith(
        "7/cerpe/lab/r0/relative_pose/r1/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/TypeHashNotSupported")
    assert ros.zenoh_key(topic, {**ros.default_conf, "key_format": "ros2dds"}) == "cerpe/lab/r0/relative_pose/r1"
    att = ros.rmw_attachment(3, 1_700_000_000_123_456_789, bytes(range(16)))
    assert len(att) == 33 and ros.parse_rmw_attachment(att) == (3, 1_700_000_000_123_456_789, bytes(range(16)))


@pytest.mark.parametrize("key_format", ros.KEY_FORMATS)
def test_publisher_puts_what_a_ros_subscriber_decodes(key_format):
    zenoh = pytest.importorskip("zenoh")
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    sessions = []
    for k, v in (("listen", [f"tcp/127.0.0.1:{port}"]), ("connect", [f"tcp/127.0.0.1:{port}"])):
        c = zenoh.Config()
        c.insert_json5("scouting/multicast/enabled", "false")
        c.insert_json5(f"{k}/endpoints", json.dumps(v))
        sessions.append(zenoh.open(c))
    pub_session, sub_session = sessions
    try:
        got, ev = [], threading.Event()
        pub = EstimatePublisher(pub_session, "lab", "r0", {"key_format": key_format})

        def on_sample(sample):
            got.append((str(sample.key_expr), sample.payload.to_bytes(),
                        None if sample.attachment is None else sample.attachment.to_bytes()))
            ev.set()

        sub = sub_session.declare_subscriber(pub.key("r1"), on_sample)
        rng = np.random.default_rng(0)
        T = random_se3(rng, 5.0)
        for _ in range(50):  # until the subscriber's declaration has reached the publisher's session
            pub.publish_pairs([PairRecord(3, 41.25, "r0", "r1", 0.9, True, "direct", T),
                               PairRecord(3, 41.25, "r0", "r2", 0.1, False, "none", None)])
            if ev.wait(0.1):
                break
        sub.undeclare()
    finally:
        for s in sessions:
            s.close()
    key, payload, attachment = got[0]
    assert key == pub.key("r1")
    msg = ros.decode_pose_cdr(payload)
    np.testing.assert_allclose(msg["T_cj_ci"], T, atol=1e-12)
    assert msg["frame_id"] == "lab/r1/camera_optical" and msg["stamp_s"] == 41.25
    assert not msg["covariance"].any()  # unknown covariance: all zeros
    if key_format == "rmw_zenoh":
        seq, _, gid = ros.parse_rmw_attachment(attachment)
        assert seq >= 1 and gid == pub.gid
    else:
        assert attachment is None
