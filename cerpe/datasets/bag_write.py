"""An encounter of any manifest written as ROS bags, one per robot, with the ``rosbag`` manifest that reads them.

What ``cerpe bag write`` does: the robots' frames (as the adapter loaded them: undistorted,
sliced, synchronised) go on ROS 2 topics under the robot's namespace, one message per frame at its
stamp: ``/<robot>/camera/image_raw`` (``Image`` rgb8, or ``/<robot>/camera/image_raw/compressed``
JPEG / PNG), ``/<robot>/camera/camera_info``, ``/<robot>/camera/depth/image_raw`` (16UC1 mm or
32FC1 m, when the robot has depth) and ``/<robot>/ground_truth/pose`` (``PoseStamped`` of the camera
in frame ``world``, when it has ground truth). So a dataset can be played to live robots
(``cerpe bag play``) and run through the ``rosbag`` adapter.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..rosio import encode
from ..rosio.bags import write_bag
from ..rosio.types import CAMERA_INFO, COMPRESSED_IMAGE, IMAGE, POSE_STAMPED
from ..scene import Encounter

IMAGE_FORMATS = ("raw", "jpeg", "png")
DEPTH_ENCODINGS = ("16UC1", "32FC1")
STORAGES = {"mcap": "", "sqlite3": "", "ros1": ".bag"}


def topics(robot: str, image_format: str = "raw") -> dict[str, str]:
    """The topics a robot's bag holds (role -> name)."""
    cam = f"/{robot}/camera"
    image = f"{cam}/image_raw" + ("" if image_format == "raw" else "/compressed")
    return {"image": image, "camera_info": f"{cam}/camera_info", "depth": f"{cam}/depth/image_raw",
            "gt": f"/{robot}/ground_truth/pose"}


def stamps(enc: Encounter, k: int, frame_rate: float | None = None) -> np.ndarray:
    """Robot ``k``'s stamps: its own, or with ``frame_rate`` step ``t`` at ``t / frame_rate`` after the
    encounter's first stamp (every robot alike: a sequence re-timed, e.g. for robots slower than its camera)."""
    if frame_rate is None:
        return np.asarray(enc.robots[k].stamps_s, dtype=np.float64)
    first = min(float(r.stamps_s[0]) for r in enc.robots)
    return first + np.arange(enc.n_steps) / float(frame_rate)


def robot_messages(enc: Encounter, k: int, image_format: str = "raw", depth_encoding: str = "16UC1",
                   frame_rate: float | None = None) -> Iterator[tuple[str, str, int, Any]]:
    """``(topic, type, bag time ns, message)`` of robot ``k`` of ``enc``, in time order."""
    rob = enc.robots[k]
    names = topics(rob.robot_id, image_format)
    frame = f"{rob.robot_id}/camera_optical"
    at = stamps(enc, k, frame_rate)
    for t in range(enc.n_steps):
        s = float(at[t])
        ns = int(round(s * 1e9))
        img = rob.image(t)
        yield names["camera_info"], CAMERA_INFO, ns, encode.camera_info(rob.intrinsics, s, frame)
        if image_format == "raw":
            yield names["image"], IMAGE, ns, encode.image(img, s, frame)
        else:
            yield names["image"], COMPRESSED_IMAGE, ns, encode.compressed(img, s, frame, image_format)
        d = rob.depth_m(t)
        if d is not None:
            yield names["depth"], IMAGE, ns, encode.depth(d, s, frame, depth_encoding)
        if rob.has_gt(t):
            yield names["gt"], POSE_STAMPED, ns, encode.pose_stamped(rob.T_world_cam[t], s, "world")


def write_encounter(enc: Encounter, out: Path | str, storage: str = "mcap", image_format: str = "raw",
                    depth_encoding: str = "16UC1", name: str | None = None,
                    frame_rate: float | None = None) -> tuple[dict[str, Path], Path]:
    """Write one bag per robot of ``enc`` into ``out`` and ``<out>/<name>.yaml``, the ``rosbag`` manifest
    that reads them (``data_root``: ``out``; metric depth ``dataset`` when every robot has depth, else
    ``none``). ``frame_rate``: re-time the frames (:func:`stamps`). Returns ``({robot: bag path}, manifest path)``."""
    if frame_rate is not None and not frame_rate > 0:
        raise ValueError(f"frame_rate must be > 0, got {frame_rate}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    name = name or f"{enc.name}-bags"
    bags = {}
    has_depth = all(r.depth is not None for r in enc.robots)
    has_gt = [bool(np.any(np.all(np.isfinite(r.T_world_cam), axis=(1, 2)))) for r in enc.robots]
    lines = [f"name: {name}", "adapter: rosbag", "data_root: .",
             f"metric_depth: {'dataset' if has_depth else 'none'}",
             "encounters:", f"  - name: {enc.name}", "    sync: index", "    robots:"]
    for k, rob in enumerate(enc.robots):
        path = out / f"{rob.robot_id}{STORAGES[storage]}"
        bags[rob.robot_id] = write_bag(path, robot_messages(enc, k, image_format, depth_encoding, frame_rate),
                                       storage)
        t = topics(rob.robot_id, image_format)
        fields = [f"id: {rob.robot_id}", f"bag: {path.name}", f"image_topic: {t['image']}",
                  f"camera_info_topic: {t['camera_info']}"]
        if has_depth:
            fields.append(f"depth_topic: {t['depth']}")
        if has_gt[k]:
            fields.append(f"gt_topic: {t['gt']}")
        lines.append("      - {" + ", ".join(fields) + "}")
    manifest = out / f"{name}.yaml"
    manifest.write_text("\n".join(lines) + "\n")
    return bags, manifest
