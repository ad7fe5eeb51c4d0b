"""``rosbag`` adapter: robots recorded as ROS bags (ROS 1 ``.bag``, ROS 2 folders, ``.db3``, ``.mcap``).

Per robot: its bag, image topic (``sensor_msgs/Image`` or ``CompressedImage``), camera info, and
optionally an aligned depth image (16UC1 mm or 32FC1 m), odometry and a ground-truth pose topic
(a motion-capture ``PoseStamped``, ``TransformStamped`` or ``Odometry``, possibly in a bag of its
own). Manifest::

    name: lab-bags
    adapter: rosbag
    data_root: /data/lab
    metric_depth: dataset              # with depth topics (none without)
    cache_dir: null                    # decoded frames; default $CERPE_CACHE/rosbag or build/rosbag
    depth_tolerance_s: 0.02            # an image's depth: the nearest depth message within this
    encounters:
      - name: run-01
        sync: stamp                    # stamp (default) | index
        robots:
          - id: r0
            bag: run-01/r0.mcap
            image_topic: /r0/camera/image_raw
            camera_info_topic: /r0/camera/camera_info   # default: camera_info beside the image topic
            depth_topic: /r0/camera/depth/image_raw     # optional
            odometry_topic: /r0/odom                    # optional (T_body_cam maps base to camera)
            gt_topic: /mocap/r0/pose                    # optional
            gt_bag: run-01/mocap.bag                    # optional: the bag holding gt_topic
            T_body_cam: identity                        # camera in the gt / odometry body frame
            gt_tolerance_s: 0.02
            interpolate: true
            interpolate_max_gap_s: 0.05
            frames: [0, 300]                            # slice fields, as tum-rgbd

Frames are the image messages (header stamps, sorted); distorted images are undistorted as they are
read (the camera info's ``plumb_bob`` / ``rational_polynomial`` coefficients, depth with nearest
neighbour). Odometry is read, checked and kept (``encounter.meta["odometry"][robot]``: ``T_odom_cam``
at each frame, NaN where none) for ``cerpe online --manifest ... --use-odometry``; the offline
methods compute their own.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..scene import CameraIntrinsics, Encounter, Setting
from . import covisibility
from .bag_frames import BagData, Topics, read_robot
from .formats import ground_truth_problems, parse_transform
from .imageref import ImageFile, Undistortion, undistortion
from .manifest import Manifest, ManifestError, Problem, cache_base, type_name
from .report import LoadReport
from .sequence import Frames, apply_slice, assemble_encounter, positive_number, validate_encounter_list, validate_slice
from .sequence import ENCOUNTER_FIELDS, SLICE_FIELDS
from .sync import nearest, poses_at

ROBOT_FIELDS = ("id", "bag", "image_topic", "camera_info_topic", "depth_topic", "odometry_topic", "gt_topic",
                "gt_bag", "T_body_cam", "gt_tolerance_s", "interpolate", "interpolate_max_gap_s") + SLICE_FIELDS
TOPIC_FIELDS = ("image_topic", "camera_info_topic", "depth_topic", "odometry_topic", "gt_topic")


def default_camera_info(image_topic: str) -> str:
    """``camera_info`` beside the image topic (``/r0/camera/image_raw`` -> ``/r0/camera/camera_info``;
    a ``.../compressed`` image transport is stepped over)."""
    parts = image_topic.rstrip("/").split("/")
    if parts[-1] in ("compressed", "compressedDepth") and len(parts) > 2:
        parts = parts[:-1]
    return "/".join(parts[:-1] + ["camera_info"])


@dataclass(frozen=True)
class NpyDepth:
    """A ``.npy`` depth map (float32 metres), undistorted with nearest neighbour like its image."""

    path: Path
    undistort: Undistortion | None = None

    def __call__(self) -> np.ndarray:
        d = np.load(self.path).astype(np.float32)
        if self.undistort is not None:
            d = self.undistort.apply(d, True, f"depth {self.path}")
        return d


def _check_robot(rob: dict, f: str, fr: str) -> list[Problem]:
    probs = []
    for k in ("bag", "image_topic"):
        if not isinstance(rob.get(k), str) or not rob.get(k):
            probs.append(Problem(f, f"{fr}.{k}", f"required: a string, got {type_name(rob.get(k))}"))
    for k in TOPIC_FIELDS + ("gt_bag",):
        if k in rob and rob[k] is not None and not (isinstance(rob[k], str) and rob[k]):
            probs.append(Problem(f, f"{fr}.{k}", f"expected a string, got {type_name(rob[k])}"))
    for k in TOPIC_FIELDS:
        if isinstance(rob.get(k), str) and not rob[k].startswith("/"):
            probs.append(Problem(f, f"{fr}.{k}", f"expected an absolute topic name (starting with /), got {rob[k]!r}"))
    if rob.get("gt_bag") and not rob.get("gt_topic"):
        probs.append(Problem(f, f"{fr}.gt_bag", "gt_bag without gt_topic"))
    return probs + ground_truth_problems(rob, f, fr) + validate_slice(rob, f, fr)


def _ordered(d: BagData, rid: str, enc: str, report: LoadReport) -> tuple[np.ndarray, list[Path]]:
    """The frames by increasing stamp, each stamp once (later duplicates counted)."""
    order = np.argsort(d.stamps_s, kind="stable")
    stamps, files = d.stamps_s[order], [d.rgb[k] for k in order]
    keep = np.concatenate([[True], np.diff(stamps) > 0])
    report.count(enc, f"{rid}: image messages with the stamp of the one before (dropped)", int((~keep).sum()))
    return stamps[keep], [p for p, k in zip(files, keep) if k]


class RosbagAdapter:
    """Robots from ROS bags (see the module docstring)."""

    name = "rosbag"
    top_level_fields: tuple[str, ...] = ("cache_dir", "depth_tolerance_s", "covisibility")

    def validate(self, manifest: Manifest) -> list[Problem]:
        f, raw = str(manifest.path), manifest.raw
        probs = positive_number(raw, "depth_tolerance_s", f, "") + covisibility.validate(manifest)
        if raw.get("cache_dir") is not None and not isinstance(raw.get("cache_dir"), str):
            probs.append(Problem(f, "cache_dir", f"expected a path string, got {type_name(raw['cache_dir'])}"))
        return probs + validate_encounter_list(manifest, ENCOUNTER_FIELDS, ROBOT_FIELDS, ("stamp", "index"), "stamp",
                                               lambda enc, f, fe: [], _check_robot)

    def load(self, manifest: Manifest, report: LoadReport) -> Setting:
        cache = (manifest.resolve(manifest.raw["cache_dir"]) if manifest.raw.get("cache_dir")
                 else cache_base() / "rosbag")
        encounters: list[Encounter] = []
        for e, enc in enumerate(manifest.encounters):
            robots, odometry = [], {}
            for r, rob in enumerate(enc["robots"]):
                got = self._robot(manifest, rob, f"encounters[{e}].robots[{r}]", enc["name"], report, cache)
                if got is not None:
                    robots.append(got[0])
                    odometry[got[0][0]] = got[1]
            if len(robots) != len(enc["robots"]):
                continue
            out = assemble_encounter(manifest, e, enc, robots, report)
            if out is not None:
                out.meta["odometry"] = self._odometry_at(out, robots, odometry)
                encounters.append(out)
        report.raise_if_problems()
        return Setting(name=manifest.name, encounters=encounters, metric_depth=manifest.metric_depth,
                       meta={"manifest": str(manifest.path), "adapter": self.name})

    @staticmethod
    def _odometry_at(enc: Encounter, robots: list, odometry: dict) -> dict[str, list]:
        """robot -> ``T_odom_cam`` at each of its encounter frames (NaN where none), as nested lists."""
        out = {}
        for rob in enc.robots:
            stamps, T_oc, gap = odometry[rob.robot_id]
            if len(stamps) == 0:
                continue
            out[rob.robot_id] = poses_at(rob.stamps_s, stamps, T_oc, gap, True, gap).tolist()
        return out

    def _robot(self, m: Manifest, rob: dict, fr: str, enc: str, report: LoadReport,
               cache: Path) -> tuple[tuple[str, CameraIntrinsics, Frames], tuple] | None:
        f, rid = str(m.path), rob["id"]
        fields = {"bag": f"{fr}.bag", "gt_bag": f"{fr}.gt_bag", "image": f"{fr}.image_topic",
                  "camera_info": f"{fr}.camera_info_topic", "depth": f"{fr}.depth_topic",
                  "odometry": f"{fr}.odometry_topic", "gt": f"{fr}.gt_topic"}
        topics = Topics(m.resolve(rob["bag"]), rob["image_topic"],
                        rob.get("camera_info_topic") or default_camera_info(rob["image_topic"]),
                        rob.get("depth_topic"), rob.get("odometry_topic"), rob.get("gt_topic"),
                        m.resolve(rob["gt_bag"]) if rob.get("gt_bag") else None)
        try:
            T_bc = parse_transform(rob.get("T_body_cam", "identity"), f"{fr}.T_body_cam", f, m.resolve)
        except ManifestError as exc:
            report.extend(exc.problems)
            return None
        data, probs = read_robot(topics, cache, f, fields)
        if data is None:
            report.extend(probs)
            return None
        for what, n in data.counts.items():
            report.count(enc, f"{rid}: {what}", n)
        K0, und = data.K, undistortion(data.K, data.dist)
        K = und.intrinsics if und is not None else K0
        stamps, rgb = _ordered(data, rid, enc, report)
        depth = None
        if rob.get("depth_topic"):
            depth = self._depth(m, data, stamps, und, K0, fields["depth"], rid, enc, report)
            if depth is None:
                return None
        tol, gap = float(rob.get("gt_tolerance_s", 0.02)), float(rob.get("interpolate_max_gap_s", 0.05))
        T = np.full((len(stamps), 4, 4), np.nan)
        if data.gt is not None:
            T = poses_at(stamps, data.gt[0], data.gt[1], tol, bool(rob.get("interpolate", True)), gap) @ T_bc
        frames = Frames(stamps, [ImageFile(p, und) for p in rgb], T, [p.stem for p in rgb], depth)
        try:
            frames = apply_slice(frames, rob, f, fr)
        except ManifestError as exc:
            report.extend(exc.problems)
            return None
        odo = (data.odometry[0], data.odometry[1] @ T_bc, gap)
        return (rid, K, frames), odo

    @staticmethod
    def _depth(m: Manifest, data: BagData, stamps: np.ndarray, und: Undistortion | None, K0: CameraIntrinsics,
               field: str, rid: str, enc: str, report: LoadReport) -> list | None:
        tol = float(m.raw.get("depth_tolerance_s", 0.02))
        idx, _ = nearest(stamps, data.depth_stamps_s, tol) if len(data.depth_stamps_s) else \
            (np.full(len(stamps), -1), None)
        sizes = {np.load(data.depth[k], mmap_mode="r").shape for k in set(int(i) for i in idx if i >= 0)}
        bad = [s for s in sizes if s != (K0.height, K0.width)]
        if bad:
            report.add(Problem(str(m.path), field, f"depth images of {bad[0][1]}x{bad[0][0]} pixels, the camera's are "
                                                   f"{K0.width}x{K0.height}: an aligned depth topic is needed "
                                                   f"(e.g. aligned_depth_to_color)"))
            return None
        report.count(enc, f"{rid}: frames without a depth message within depth_tolerance_s", int((idx < 0).sum()))
        return [NpyDepth(data.depth[int(k)], und) if k >= 0 else None for k in idx]
