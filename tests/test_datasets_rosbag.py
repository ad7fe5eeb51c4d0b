"""The ``rosbag`` adapter: an encounter written as bags (cerpe.datasets.bag_write) reads back as itself.

Every bag kind (ROS 2 mcap and sqlite3 folders, a bare .mcap, ROS 1 .bag; raw, PNG and JPEG images),
distorted cameras undistorted as a live robot does, ground truth from a topic of another bag,
odometry kept for the online replay; and what cannot be used, each one problem naming the field:
a topic the bag does not hold (listing what it holds), a bag cut short, a CameraInfo of zeros,
depth of another size, the wrong message type on a topic, a message that does not decode (counted).
"""
from __future__ import annotations

import numpy as np
import pytest

from cerpe.datasets import load_setting
from cerpe.datasets.bag_write import robot_messages, topics, write_encounter
from cerpe.datasets.imageref import undistortion
from cerpe.datasets.manifest import ManifestError
from cerpe.geometry import make_se3
from cerpe.rosio import encode
from cerpe.rosio import types as rt
from cerpe.rosio.bags import write_bag
from gt_backbone import make_world

WORLD = make_world(2, 5, seed=2)
ENC = WORLD.to_encounter("enc")


def manifest(tmp_path, robots: str, extra: str = "") -> str:
    m = tmp_path / "m.yaml"
    m.write_text(f"name: bags\nadapter: rosbag\ndata_root: .\nmetric_depth: dataset\ncache_dir: cache\n{extra}"
                 f"encounters:\n  - name: enc\n    sync: index\n    robots:\n{robots}")
    return str(m)


def robot_line(rid: str, bag: str, **fields) -> str:
    t = topics(rid)
    base = {"id": rid, "bag": bag, "image_topic": t["image"], **fields}
    return "      - {" + ", ".join(f"{k}: {v}" for k, v in base.items()) + "}\n"


def assert_same(enc, got, image_atol=0):
    assert got.robot_ids == enc.robot_ids and got.n_steps == enc.n_steps
    for a, b in zip(enc.robots, got.robots):
        assert a.intrinsics == b.intrinsics
        np.testing.assert_array_equal(a.stamps_s, b.stamps_s)
        np.testing.assert_allclose(a.T_world_cam, b.T_world_cam, atol=1e-9)
        for t in range(enc.n_steps):
            assert np.abs(a.image(t).astype(int) - b.image(t)).max() <= image_atol
            np.testing.assert_allclose(a.depth_m(t), b.depth_m(t), atol=5e-4 + 1e-6)


@pytest.mark.parametrize("storage, image_format, atol", [("mcap", "raw", 0), ("sqlite3", "png", 0),
                                                         ("ros1", "jpeg", 255)])
def test_written_bags_read_back(tmp_path, storage, image_format, atol):
    bags, m = write_encounter(ENC, tmp_path / "bags", storage, image_format)
    setting = load_setting(m)
    assert_same(ENC, setting.encounters[0], image_atol=atol)  # noise images: JPEG only keeps the size
    assert setting.encounters[0].meta["odometry"] == {}
    again = load_setting(m)  # from the frame cache
    assert_same(setting.encounters[0], again.encounters[0])


def test_bare_mcap_distortion_gt_bag_and_odometry(tmp_path):
    """A bare .mcap per robot, a distorted camera, ground truth in a bag of its own, odometry."""
    dist = (0.05, -0.02, 0.0, 0.0, 0.0)
    K = ENC.robots[0].intrinsics
    msgs, gt = [], []
    for k, rob in enumerate(ENC.robots):
        for topic, kind, ns, msg in robot_messages(ENC, k):
            if kind == rt.CAMERA_INFO:
                msg = encode.camera_info(K, ns * 1e-9, "cam", dist)
            (gt if topic.endswith("/pose") else msgs).append((topic, kind, ns, msg))
        for t in range(ENC.n_steps):
            s = float(rob.stamps_s[t])
            msgs.append((f"/{rob.robot_id}/odom", rt.ODOMETRY, int(s * 1e9) + 1,
                         encode.odometry(make_se3(np.eye(3), [t, 0, 0]), s)))
    for rob in ENC.robots:
        own = sorted((m for m in msgs if m[0].startswith(f"/{rob.robot_id}/")), key=lambda m: m[2])
        write_bag(tmp_path / f"{rob.robot_id}-dir", own, "mcap")
    write_bag(tmp_path / "mocap.bag", sorted(gt, key=lambda m: m[2]), "ros1")
    robots = "".join(robot_line(r, f"{r}-dir/{r}-dir.mcap", camera_info_topic=topics(r)["camera_info"],
                                gt_topic=topics(r)["gt"], gt_bag="mocap.bag", odometry_topic=f"/{r}/odom",
                                depth_topic=topics(r)["depth"])
                     for r in ENC.robot_ids)
    got = load_setting(manifest(tmp_path, robots)).encounters[0]
    und = undistortion(K, dist)
    assert got.robots[0].intrinsics == und.intrinsics
    raw = ENC.robots[1].image(2)
    np.testing.assert_array_equal(got.robots[1].image(2), und.apply(raw[:, :, ::-1], False, "x")[:, :, ::-1])
    np.testing.assert_allclose(got.robots[0].T_world_cam, ENC.robots[0].T_world_cam, atol=1e-9)
    odo = np.asarray(got.meta["odometry"]["r1"])
    np.testing.assert_allclose(odo[:, 0, 3], np.arange(ENC.n_steps), atol=1e-6)  # at the image stamps


def test_what_cannot_be_used_is_one_problem_each(tmp_path):
    bags, _ = write_encounter(ENC, tmp_path / "b", "mcap")
    rel = {r: f"b/{p.name}" for r, p in bags.items()}
    with pytest.raises(ManifestError) as err:
        load_setting(manifest(tmp_path, robot_line("r0", rel["r0"], depth_topic="/r0/nope")
                              + robot_line("r1", rel["r1"], gt_topic="/r1/camera/camera_info")))
    text = str(err.value)
    assert "encounters[0].robots[0].depth_topic: topic /r0/nope is not in bag" in text and "/r0/camera/image_raw (" \
        in text
    assert "encounters[0].robots[1].gt_topic: topic /r1/camera/camera_info" in text and "carries sensor_msgs/msg/Camera" \
        in text
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(next((tmp_path / "b" / "r0").glob("*.mcap")).read_bytes()[:5000])
    with pytest.raises(ManifestError, match=r"robots\[0\].bag: .*cut.mcap does not open as a ROS bag.*mcap recover"):
        load_setting(manifest(tmp_path, robot_line("r0", "cut.mcap") + robot_line("r1", rel["r1"])))
    with pytest.raises(ManifestError, match=r"robots\[0\].image_topic: required"):
        load_setting(manifest(tmp_path, "      - {id: r0, bag: x}\n" + robot_line("r1", rel["r1"])))


def test_bad_messages_in_a_bag(tmp_path):
    """Zeros in every CameraInfo: one problem; depth of another size: one problem; an image that
    does not decode: counted, the others read."""
    def bag(name, change):
        msgs = [change(m) for m in robot_messages(ENC, 0)]
        return write_bag(tmp_path / name, [m for m in msgs if m is not None], "mcap").name

    def zero_info(m):
        if m[1] == rt.CAMERA_INFO:
            m[3].k = np.zeros(9)
        return m

    def small_depth(m):
        if m[0].endswith("depth/image_raw"):
            return m[0], m[1], m[2], encode.depth(np.ones((4, 4)), m[2] * 1e-9, "cam")
        return m

    def one_bad_image(m):
        if m[1] == rt.IMAGE and m[0].endswith("image_raw") and "depth" not in m[0] and m[2] == ENC.robots[0].stamps_s[1] * 1e9:
            m[3].encoding = "yuv422"
        return m

    good = write_bag(tmp_path / "r1", robot_messages(ENC, 1), "mcap").name
    with pytest.raises(ManifestError, match=r"robots\[0\].camera_info_topic: no usable CameraInfo.*fx=0, fy=0"):
        load_setting(manifest(tmp_path, robot_line("r0", bag("zero", zero_info)) + robot_line("r1", good)))
    with pytest.raises(ManifestError, match=r"robots\[0\].depth_topic: depth images of 4x4 pixels"):
        load_setting(manifest(tmp_path, robot_line("r0", bag("small", small_depth), depth_topic=topics("r0")["depth"])
                              + robot_line("r1", good)))
    s = load_setting(manifest(tmp_path, robot_line("r0", bag("bad", one_bad_image)) + robot_line("r1", good)))
    assert s.encounters[0].n_steps == ENC.n_steps - 1
    counts = s.meta["load_report"]["counts"]
    assert any("messages that do not decode" in k and "yuv422" in k and n == 1 for k, n in counts.items()), counts
