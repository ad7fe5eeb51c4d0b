"""cerpe.rosio and cerpe.stamped_poses: ROS messages to numpy and back, bags, a TF buffer, poses by stamp.

Round trips (what a bag or a live topic carries decodes to what was written), every bad message a
live robot may get (unsupported encoding, a CameraInfo of zeros, NaN odometry, the wrong type, cut
data) raising one RosInputError that names what is wrong, and interpolation with known answers.
"""
from __future__ import annotations

import numpy as np
import pytest

from cerpe.geometry import make_se3, random_se3, rotation_angle, se3_inverse, so3_exp
from cerpe.rosio import RosInputError, decode, encode
from cerpe.rosio import types as rt
from cerpe.rosio.bags import BagError, BagReader, to_ros1, to_ros2, write_bag
from cerpe.rosio.tf import TfBuffer
from cerpe.scene import CameraIntrinsics
from cerpe.stamped_poses import StampedPoses

RNG = np.random.default_rng(0)
RGB = RNG.integers(0, 255, (24, 32, 3), dtype=np.uint8)
K = CameraIntrinsics(30.0, 31.0, 15.5, 11.5, 32, 24)


def cdr_round_trip(msg, kind):
    return rt.deserialize(rt.serialize(msg, kind), kind, "/t")


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8"])
def test_colour_images_round_trip(encoding):
    assert np.array_equal(decode.image_rgb(cdr_round_trip(encode.image(RGB, 5.25, "cam", encoding), rt.IMAGE), "/t"), RGB)
    mono = decode.image_rgb(encode.image(RGB, 1.0, "cam", "mono8"), "/t")
    assert mono.shape == RGB.shape and np.all(mono[..., 0] == mono[..., 2])
    png = cdr_round_trip(encode.compressed(RGB, 1.0, "cam", "png"), rt.COMPRESSED_IMAGE)
    assert np.array_equal(decode.image_rgb(png, "/t"), RGB)
    smooth = np.zeros((24, 32, 3), np.uint8)
    smooth[..., 0], smooth[..., 2] = np.arange(32) * 8, np.arange(24)[:, None] * 10  # red right, blue down
    jpg = decode.image_rgb(encode.compressed(smooth, 1.0, "cam", "jpeg"), "/t")
    assert jpg.shape == RGB.shape and np.abs(jpg.astype(int) - smooth).mean() < 4


def test_padded_rows_and_bgra_are_read():
    msg = encode.image(RGB, 1.0, "cam", "bgr8")
    rows = np.asarray(msg.data).reshape(24, 96)
    msg.data = np.concatenate([np.concatenate([rows[:, k * 3:k * 3 + 3], np.full((24, 1), 7, np.uint8)], axis=1)
                               for k in range(32)] + [np.zeros((24, 8), np.uint8)], axis=1).ravel()
    msg.encoding, msg.step = "bgra8", 32 * 4 + 8
    assert np.array_equal(decode.image_rgb(msg, "/t"), RGB)


def test_depth_encodings():
    d = RNG.uniform(0.3, 6.0, (24, 32)).astype(np.float32)
    d[0, 0], d[0, 1], d[0, 2] = np.nan, -1.0, np.inf
    mm = decode.depth_m(cdr_round_trip(encode.depth(d, 1.0, "cam", "16UC1"), rt.IMAGE), "/t")
    np.testing.assert_allclose(mm[1:], d[1:], atol=5e-4 + 1e-6)
    assert mm[0, :3].tolist() == [0.0, 0.0, 0.0]
    m = decode.depth_m(encode.depth(d, 1.0, "cam", "32FC1"), "/t")
    assert np.array_equal(m[1:], d[1:]) and m[0, :3].tolist() == [0.0, 0.0, 0.0]
    big = encode.depth(d, 1.0, "cam", "16UC1")
    big.data = np.asarray(big.data).reshape(-1, 2)[:, ::-1].ravel().copy()
    big.is_bigendian = 1
    np.testing.assert_array_equal(decode.depth_m(big, "/t"), mm)


def test_camera_info_and_poses():
    got = decode.camera(cdr_round_trip(encode.camera_info(K, 1.0, "cam", [0.1, -0.2, 0.0, 0.0, 0.01]), rt.CAMERA_INFO), "/i")
    assert got == (K, (0.1, -0.2, 0.0, 0.0, 0.01))
    X = random_se3(RNG, 3.0)
    for msg, kind in ((encode.odometry(X, 2.0), rt.ODOMETRY), (encode.pose_stamped(X, 2.0, "world"), rt.POSE_STAMPED),
                      (encode.transform(X, 2.0, "odom", "base"), rt.TRANSFORM_STAMPED)):
        np.testing.assert_allclose(decode.pose(cdr_round_trip(msg, kind), "/p"), X, atol=1e-12)
        assert decode.stamp_s(msg) == 2.0
    assert decode.frames(encode.transform(X, 2.0, "/odom", "base")) == ("odom", "base")


def test_ros1_messages_read_as_ros2():
    ci = encode.camera_info(K, 3.5, "cam")
    r1 = to_ros1(ci)
    assert hasattr(r1, "K") and r1.header.seq == 0
    back = to_ros2(r1)
    assert decode.camera(back, "/i") == decode.camera(ci, "/i") and decode.stamp_s(back) == 3.5


@pytest.mark.parametrize("change, match", [
    (lambda m: setattr(m, "encoding", "yuv422"), "encoding 'yuv422' is not supported"),
    (lambda m: setattr(m, "data", np.asarray(m.data)[:100]), "does not hold 24 rows"),
    (lambda m: setattr(m, "height", 0), "image of 32x0 pixels"),
])
def test_bad_images(change, match):
    msg = encode.image(RGB, 1.0, "cam")
    change(msg)
    with pytest.raises(RosInputError, match=match):
        decode.image_rgb(msg, "/cam/image_raw")


def test_bad_messages_name_what_is_wrong():
    bad = encode.compressed(RGB, 1.0, "cam")
    bad.data = np.frombuffer(b"not a jpeg", np.uint8)
    with pytest.raises(RosInputError, match="/c: CompressedImage of format 'jpeg'.*does not decode"):
        decode.image_rgb(bad, "/c")
    with pytest.raises(RosInputError, match="CameraInfo message where an image"):
        decode.image_rgb(encode.camera_info(K, 1.0, "cam"), "/c")
    with pytest.raises(RosInputError, match="depth encoding 'rgb8'"):
        decode.depth_m(encode.image(RGB, 1.0, "cam"), "/d")
    zeros = encode.camera_info(K, 1.0, "cam")
    zeros.k = np.zeros(9)
    with pytest.raises(RosInputError, match="/i: CameraInfo k has fx=0, fy=0"):
        decode.camera(zeros, "/i")
    fish = encode.camera_info(K, 1.0, "cam", [0.1, 0.0, 0.0, 0.0])
    fish.distortion_model = "equidistant"
    with pytest.raises(RosInputError, match="distortion_model 'equidistant' is not supported"):
        decode.camera(fish, "/i")
    odo = encode.odometry(np.eye(4), 1.0)
    odo.pose.pose.position.x = float("nan")
    with pytest.raises(RosInputError, match="/odom: nav_msgs/msg/Odometry pose holds NaN"):
        decode.pose(odo, "/odom")
    with pytest.raises(RosInputError, match="/x: not a CDR sensor_msgs/msg/Image"):
        rt.deserialize(rt.serialize(encode.odometry(np.eye(4), 1.0), rt.ODOMETRY)[:40], rt.IMAGE, "/x")


def test_bags_of_every_kind_read_back(tmp_path):
    X = random_se3(RNG, 1.0)
    msgs = [("/r/image", rt.IMAGE, k * 10**9 + 1, encode.image(RGB, k + 1e-9, "cam")) for k in range(3)]
    msgs += [("/r/info", rt.CAMERA_INFO, 2 * 10**9, encode.camera_info(K, 2.0, "cam")),
             ("/r/odom", rt.ODOMETRY, 3 * 10**9, encode.odometry(X, 3.0))]
    msgs.sort(key=lambda m: m[2])
    paths = [write_bag(tmp_path / "a", msgs, "mcap"), write_bag(tmp_path / "b", msgs, "sqlite3"),
             write_bag(tmp_path / "c.bag", msgs, "ros1")]
    paths += [next((tmp_path / "a").glob("*.mcap")), next((tmp_path / "b").glob("*.db3"))]
    for p in paths:
        with BagReader(p) as r:
            assert r.topics == {"/r/image": rt.IMAGE, "/r/info": rt.CAMERA_INFO, "/r/odom": rt.ODOMETRY}
            got = list(r.messages(r.topics))
        assert [g[2] for g in got] == [m[2] for m in msgs], p
        assert np.array_equal(decode.image_rgb(got[0][3], "/r/image"), RGB)
        assert decode.camera(next(g[3] for g in got if g[0] == "/r/info"), "/r/info")[0] == K
        np.testing.assert_allclose(decode.pose(got[-1][3], "/r/odom"), X, atol=1e-12)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(paths[3].read_bytes()[:2000])
    with pytest.raises(BagError, match=r"cut.mcap does not open as a ROS bag.*`mcap recover`"):
        BagReader(cut)
    with pytest.raises(BagError, match="not a bag"):
        BagReader(tmp_path / "a" / "metadata.yaml")
    with pytest.raises(BagError, match="bag not found"):
        BagReader(tmp_path / "none.bag")


def test_tf_buffer_chains_static_transforms_and_reads_the_moving_one():
    T_base_link, T_link_opt = random_se3(RNG, 0.3), random_se3(RNG, 0.1)
    tf = TfBuffer("odom", "base_link")
    tf.add_static(encode.tf_message([encode.transform(T_base_link, 0.0, "base_link", "camera_link"),
                                     encode.transform(T_link_opt, 0.0, "camera_link", "camera_optical")]), "/tf_static")
    np.testing.assert_allclose(tf.static_T("base_link", "camera_optical"), T_base_link @ T_link_opt, atol=1e-12)
    assert tf.static_T("base_link", "elsewhere") is None
    moves = [make_se3(np.eye(3), [k, 0.0, 0.0]) for k in range(3)]
    for k, T in enumerate(moves):
        tf.add_dynamic(encode.tf_message([encode.transform(T, float(k), "odom", "base_link"),
                                          encode.transform(T, float(k), "map", "odom")]), "/tf")
    T, how = tf.moving.at(1.25, 2.0, 0.5)
    assert how == "interpolated" and np.allclose(T[:3, 3], [1.25, 0, 0])


def test_stamped_poses_interpolate_and_bound_the_extrapolation():
    s = StampedPoses(keep=4)
    assert s.at(0.0, 1.0, 1.0) == (None, "none")
    R = so3_exp(np.array([0.0, 0.2, 0.0]))
    for k in range(5):
        assert s.add(float(k), make_se3(np.linalg.matrix_power(R, k), [2.0 * k, 0.0, 0.0]))
    assert not s.add(4.0, np.eye(4)) and not s.add(5.0, np.full((4, 4), np.nan)) and len(s) == 4
    assert s.add(2.75, make_se3(np.eye(3), [0.0, 9.0, 0.0])) and s.stamps == [2.0, 2.75, 3.0, 4.0]  # in stamp order
    s = StampedPoses(keep=4)
    for k in range(5):
        s.add(float(k), make_se3(np.linalg.matrix_power(R, k), [2.0 * k, 0.0, 0.0]))
    T, how = s.at(2.0, 1.5, 0.5)
    assert how == "exact" and np.allclose(T[:3, 3], [4, 0, 0])
    T, how = s.at(2.5, 1.5, 0.5)
    assert how == "interpolated" and np.allclose(T[:3, 3], [5, 0, 0])
    assert np.isclose(rotation_angle((se3_inverse(s.at(2.0, 1.5, 0.5)[0]) @ T)[:3, :3]), 0.1)
    T, how = s.at(4.4, 1.5, 0.5)  # constant velocity: 2 m and 0.2 rad per second
    assert how == "extrapolated" and np.allclose(T[:3, 3], [8.8, 0, 0]) and np.isclose(rotation_angle(T[:3, :3]), 0.88)
    assert s.at(4.6, 1.5, 0.5) == (None, "too-far")
    assert s.at(0.7, 1.5, 0.5)[1] == "extrapolated" and s.at(0.4, 1.5, 0.5)[1] == "too-far"  # before the oldest: held
    assert s.at(2.5, 0.9, 0.5) == (None, "gap")
