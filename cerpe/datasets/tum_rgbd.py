"""``tum-rgbd`` adapter: TUM RGB-D benchmark sequence folders, one (or a slice of one) per robot.

A sequence folder (``rgbd_dataset_freiburg1_desk/``) holds ``rgb.txt`` and
``depth.txt`` (``stamp path`` lines), ``rgb/``, ``depth/`` (16-bit PNG, 5000 units
per metre, 0 = no measurement) and ``groundtruth.txt`` (TUM trajectory: the
colour camera's optical centre in the motion-capture world, OpenCV axes).
Manifest::

    name: tum-desk-pair
    adapter: tum-rgbd
    data_root: /data/tum
    metric_depth: dataset
    association_tolerance_s: 0.02      # rgb <-> depth, as associate.py's --max_difference
    covisibility: auto                 # auto: overlap from depth + poses (cached) | off
    encounters:
      - name: desk
        sync: index                    # index (default) | stamp
        robots:
          - id: a
            sequence: rgbd_dataset_freiburg1_desk
            camera: fr1                # fr1 | fr2 | fr3 | ros-default | path/to/camera.yaml; default from the folder name
            depth: true                # false: RGB only (depth.txt not read)
            depth_units_per_m: 5000
            gt_tolerance_s: 0.02       # nearest pose within this, else NaN (counted)
            interpolate: true          # SLERP between poses at most interpolate_max_gap_s apart
            interpolate_max_gap_s: 0.05
            frames: [0, 300]           # optional slice, see cerpe.datasets.sequence
          - {id: b, sequence: rgbd_dataset_freiburg1_desk2}

Colour and depth are associated as TUM's ``associate.py`` does (pairs closer than
the tolerance, closest first, each stamp once); colour frames without depth are
dropped and counted, and none at all is an error naming the files. fr1 and fr2
images are distorted: they are undistorted once per frame as they are read
(OpenCV, maps computed once per camera), depth with nearest-neighbour sampling,
and the robot gets the pinhole intrinsics of the undistorted images. Calibration
of the named cameras: TUM RGB-D "file formats" page (colour camera, fr1/fr2/fr3).
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..scene import CameraIntrinsics, Setting
from . import covisibility
from .formats import NONFINITE_ROWS, file_problems, read_camera, read_list_file, read_trajectory
from .imageref import DepthFile, ImageFile, Undistortion, undistortion
from .manifest import Manifest, ManifestError, Problem
from .report import LoadReport
from .sequence import Frames, apply_slice, load_encounters, positive_number, validate_encounters
from .sync import associate, nearest, poses_at

WIDTH, HEIGHT = 640, 480
DEPTH_UNITS_PER_M = 5000.0
# colour camera: (fx, fy, cx, cy), OpenCV distortion (k1, k2, p1, p2, k3)
CAMERAS: dict[str, tuple[tuple[float, ...], tuple[float, ...]]] = {
    "fr1": ((517.3, 516.5, 318.6, 255.3), (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "fr2": ((520.9, 521.0, 325.1, 249.7), (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "fr3": ((535.4, 539.2, 320.1, 247.6), (0.0, 0.0, 0.0, 0.0, 0.0)),
    "ros-default": ((525.0, 525.0, 319.5, 239.5), (0.0, 0.0, 0.0, 0.0, 0.0)),
}
ROBOT_FIELDS = ("id", "sequence", "camera", "depth", "depth_units_per_m", "gt_tolerance_s", "interpolate",
                "interpolate_max_gap_s")


def camera_of(rob: dict, seq: Path) -> str | None:
    """The robot's camera: its ``camera`` value, else ``frN`` from a ``freiburgN`` folder name."""
    if rob.get("camera"):
        return str(rob["camera"])
    hit = re.search(r"freiburg(\d)", seq.name)
    return f"fr{hit.group(1)}" if hit and f"fr{hit.group(1)}" in CAMERAS else None


def _check_robot(rob: dict, f: str, fr: str) -> list[Problem]:
    probs = []
    cam = rob.get("camera")
    if cam is not None and not (isinstance(cam, str) and (cam in CAMERAS or cam.endswith((".yaml", ".yml")))):
        probs.append(Problem(f, f"{fr}.camera", f"expected one of {', '.join(CAMERAS)} or a camera .yaml file, got {cam!r}"))
    for k in ("depth", "interpolate"):
        if k in rob and not isinstance(rob[k], bool):
            probs.append(Problem(f, f"{fr}.{k}", f"expected true or false, got {rob[k]!r}"))
    for k in ("depth_units_per_m", "gt_tolerance_s", "interpolate_max_gap_s"):
        probs += positive_number(rob, k, f, fr)
    return probs


class TumRgbdAdapter:
    """TUM RGB-D sequences (rgb.txt, depth.txt, groundtruth.txt) as robots."""

    name = "tum-rgbd"
    top_level_fields: tuple[str, ...] = ("association_tolerance_s", "covisibility")

    def validate(self, manifest: Manifest) -> list[Problem]:
        f, raw = str(manifest.path), manifest.raw
        probs = positive_number(raw, "association_tolerance_s", f, "")
        probs += covisibility.validate(manifest)
        return probs + validate_encounters(manifest, ROBOT_FIELDS, ("sequence",), _check_robot)

    def load(self, manifest: Manifest, report: LoadReport) -> Setting:
        cams: dict[str, tuple[CameraIntrinsics, Undistortion | None]] = {}
        encounters = load_encounters(manifest, report, lambda rob, fr, enc: self._robot(manifest, rob, fr, enc, report, cams))
        return Setting(name=manifest.name, encounters=encounters, metric_depth=manifest.metric_depth,
                       meta={"manifest": str(manifest.path), "adapter": self.name})

    def _camera(self, m: Manifest, rob: dict, seq: Path, fr: str,
                cams: dict) -> tuple[CameraIntrinsics, Undistortion | None]:
        cam = camera_of(rob, seq)
        if cam is None:
            raise ManifestError([Problem(str(m.path), f"{fr}.camera", f"cannot tell the camera from the folder name "
                                         f"{seq.name!r}: set camera: {' | '.join(CAMERAS)} or a camera .yaml")])
        if cam not in cams:
            if cam in CAMERAS:
                (fx, fy, cx, cy), dist = CAMERAS[cam]
                K = CameraIntrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=WIDTH, height=HEIGHT)
            else:
                K, dist = read_camera(m.resolve(cam), f"{fr}.camera")
            und = undistortion(K, dist)
            cams[cam] = (und.intrinsics if und is not None else K, und)
        return cams[cam]

    def _robot(self, m: Manifest, rob: dict, fr: str, enc: str, report: LoadReport,
               cams: dict) -> tuple[str, CameraIntrinsics, Frames]:
        rid = rob["id"]
        seq = m.resolve(rob["sequence"])
        rgb_txt = seq / "rgb.txt"
        if not rgb_txt.is_file():
            what = "sequence folder not found" if not seq.is_dir() else \
                "rgb.txt not found (a TUM RGB-D sequence folder holds rgb.txt, depth.txt and groundtruth.txt)"
            raise ManifestError([Problem(str(rgb_txt if seq.is_dir() else seq), f"{fr}.sequence", what)])
        K, und = self._camera(m, rob, seq, fr, cams)
        stamps, rgb, lines = read_list_file(rgb_txt, f"{fr}.sequence rgb.txt")
        size = (und.K if und is not None else K).width, (und.K if und is not None else K).height
        probs = file_problems([(p, f"{fr}.sequence rgb.txt line {k}") for p, k in zip(rgb, lines)],
                              "colour image listed in rgb.txt", size)
        depth = None
        if rob.get("depth", True):
            depth_txt = seq / "depth.txt"
            if not depth_txt.is_file():
                raise ManifestError(probs + [Problem(str(depth_txt), f"{fr}.sequence", "depth.txt not found (set depth: false "
                                                                                     "for RGB only)")])
            d_stamps, d_paths, d_lines = read_list_file(depth_txt, f"{fr}.sequence depth.txt")
            tol = float(m.raw.get("association_tolerance_s", 0.02))
            i_rgb, i_depth = associate(stamps, d_stamps, tol)
            if len(i_rgb) == 0:
                j, dt = nearest(stamps[:1], d_stamps, np.inf)
                raise ManifestError(probs + [Problem(
                    str(rgb_txt), f"{fr}.sequence rgb.txt line {lines[0]}",
                    f"no colour stamp has a depth stamp within association_tolerance_s={tol:g} s "
                    f"(the first, {stamps[0]:.6f}, is {abs(dt[0]):.3f} s from {depth_txt.name} line {d_lines[j[0]]}); "
                    "are both lists from the same sequence?")])
            report.count(enc, f"{rid}: colour frames without depth within association_tolerance_s (dropped)",
                         len(stamps) - len(i_rgb))
            probs += file_problems([(d_paths[j], f"{fr}.sequence depth.txt line {d_lines[j]}") for j in i_depth],
                                   "depth image listed in depth.txt", size, min_bits=16)
            units = float(rob.get("depth_units_per_m", DEPTH_UNITS_PER_M))
            depth = [DepthFile(d_paths[j], units, (), und) for j in i_depth]
            stamps, rgb = stamps[i_rgb], [rgb[i] for i in i_rgb]
        if probs:
            raise ManifestError(probs)
        T = np.full((len(stamps), 4, 4), np.nan)
        gt = seq / "groundtruth.txt"
        if gt.is_file():
            traj = read_trajectory(gt, "tum", f"{fr}.sequence groundtruth.txt")
            report.count(enc, f"{rid}: {NONFINITE_ROWS}", traj.n_nan_rows)
            T = poses_at(stamps, traj.stamps_s, traj.T_world_body, float(rob.get("gt_tolerance_s", 0.02)),
                         bool(rob.get("interpolate", True)), float(rob.get("interpolate_max_gap_s", 0.05)))
        images = [ImageFile(p, und) if und is not None else p for p in rgb]
        frames = Frames(stamps, images, T, [p.stem for p in rgb], depth)
        return rid, K, apply_slice(frames, rob, str(m.path), fr)

