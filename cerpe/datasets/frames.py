"""``frames`` adapter: folders of ``frame-NNNNNN.{color,depth,pose}`` files (7-Scenes, 3DMatch, SUN3D).

Each robot is one folder (or a slice of one, see :mod:`cerpe.datasets.sequence`)::

    <folder>/frame-000000.color.png   # colour (png or jpg)
    <folder>/frame-000000.depth.png   # optional: 16-bit, millimetres; 0 and 65535 = no measurement
    <folder>/frame-000000.pose.txt    # optional: 4x4 camera-to-world, metres (non-finite = unknown)

Manifest::

    name: sun3d-two-fragments
    adapter: frames
    data_root: /data/sun3d
    intrinsics: camera-intrinsics.txt   # 3x3 matrix text file | camera.yaml | {fx: 585, fy: 585, cx: 320, cy: 240}
    rate_hz: 30                         # stamps = frame number / rate_hz (the packaging has none)
    depth_units_per_m: 1000
    metric_depth: dataset
    covisibility: auto                  # auto: overlap from depth + poses (cached) | off
    encounters:
      - name: fragments
        sync: index                     # index (default) | stamp
        robots:
          - {id: f1, folder: fragment-1}
          - {id: f2, folder: fragment-2, frames: [0, 25], stride: 2}

``intrinsics``, ``rate_hz``, ``depth_units_per_m`` may also be set per robot;
``depth: false`` ignores depth files. Frame numbers give the stamps, so two
folders of one recording keep their true time gap. 7-Scenes ships no intrinsics
file: its usual values are ``{fx: 585, fy: 585, cx: 320, cy: 240}`` (its depth is
not registered to colour).
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from ..geometry import GeometryError, check_se3
from ..scene import CameraIntrinsics, SceneError, Setting
from . import covisibility
from .formats import file_problems, image_size, read_intrinsics, read_matrix
from .imageref import DepthFile
from .manifest import Manifest, ManifestError, Problem, is_number
from .report import LoadReport
from .sequence import Frames, apply_slice, load_encounters, positive_number, validate_encounters

FRAME_RE = re.compile(r"^frame-(\d+)\.color\.(png|jpg|jpeg)$", re.IGNORECASE)
INVALID_DEPTH = (65535,)
POSE_ATOL = 1e-3  # packaged poses are printed with ~6 digits
TOP_LEVEL = ("intrinsics", "rate_hz", "depth_units_per_m", "covisibility")
ROBOT_FIELDS = ("id", "folder", "intrinsics", "rate_hz", "depth", "depth_units_per_m")


def _check_intrinsics(v: Any, f: str, field: str) -> list[Problem]:
    if isinstance(v, str) and v:
        return []
    if isinstance(v, dict):
        bad = [k for k in ("fx", "fy", "cx", "cy") if not is_number(v.get(k))]
        extra = [k for k in v if k not in ("fx", "fy", "cx", "cy")]
        if not bad and not extra:
            return []
    return [Problem(f, field, f"expected a file (3x3 matrix text or camera.yaml) or {{fx, fy, cx, cy}}, got {v!r}")]


def _check_common(obj: dict, f: str, fr: str) -> list[Problem]:
    probs = positive_number(obj, "rate_hz", f, fr) + positive_number(obj, "depth_units_per_m", f, fr)
    if "intrinsics" in obj:
        probs += _check_intrinsics(obj["intrinsics"], f, f"{fr}.intrinsics" if fr else "intrinsics")
    if "depth" in obj and not isinstance(obj["depth"], bool):
        probs.append(Problem(f, f"{fr}.depth", f"expected true or false, got {obj['depth']!r}"))
    return probs


def read_frame_intrinsics(value: Any, m: Manifest, field: str, size: tuple[int, int]) -> CameraIntrinsics:
    """Intrinsics from a 3x3 matrix text file, a camera.yaml, or an ``{fx, fy, cx, cy}`` mapping (size from the images)."""
    if isinstance(value, str) and value.endswith((".yaml", ".yml")):
        K = read_intrinsics(m.resolve(value), field)
        if (K.width, K.height) != tuple(size):
            raise ManifestError([Problem(str(m.resolve(value)), field, f"camera is {K.width}x{K.height}, "
                                                                        f"the images are {size[0]}x{size[1]}")])
        return K
    if isinstance(value, str):
        path = m.resolve(value)
        M = read_matrix(path, field, (3, 3), "intrinsics")
        if not np.allclose([M[1, 0], M[2, 0], M[2, 1], M[2, 2]], [0, 0, 0, 1], atol=1e-9):
            raise ManifestError([Problem(str(path), field, f"not a calibration matrix [[fx 0 cx] [0 fy cy] [0 0 1]]: {M.tolist()}")])
        vals = (M[0, 0], M[1, 1], M[0, 2], M[1, 2])
    else:
        vals = (value["fx"], value["fy"], value["cx"], value["cy"])
    try:
        return CameraIntrinsics(*(float(v) for v in vals), width=size[0], height=size[1])
    except SceneError as exc:
        raise ManifestError([Problem(str(m.path), field, str(exc))]) from None


def read_pose(path: Path, field: str) -> np.ndarray:
    """A ``frame-*.pose.txt`` 4x4 camera-to-world; NaN when it holds non-finite numbers (unknown pose)."""
    T = read_matrix(path, field, (4, 4), "pose")
    if not np.all(np.isfinite(T)):
        return np.full((4, 4), np.nan)
    try:
        return check_se3(T, "pose", atol=POSE_ATOL)
    except GeometryError as exc:
        raise ManifestError([Problem(str(path), field, f"not a rigid transform ({str(exc).removeprefix('pose: ')})")]) from None


class FramesAdapter:
    """7-Scenes / 3DMatch / SUN3D frame folders as robots."""

    name = "frames"
    top_level_fields: tuple[str, ...] = TOP_LEVEL

    def validate(self, manifest: Manifest) -> list[Problem]:
        f, raw = str(manifest.path), manifest.raw
        probs = _check_common({k: raw[k] for k in TOP_LEVEL if k in raw and k != "covisibility"}, f, "")
        probs += covisibility.validate(manifest)
        return probs + validate_encounters(manifest, ROBOT_FIELDS, ("folder",), _check_common)

    def load(self, manifest: Manifest, report: LoadReport) -> Setting:
        encounters = load_encounters(manifest, report, lambda rob, fr, enc: self._robot(manifest, rob, fr, enc, report))
        return Setting(name=manifest.name, encounters=encounters, metric_depth=manifest.metric_depth,
                       meta={"manifest": str(manifest.path), "adapter": self.name})

    def _robot(self, m: Manifest, rob: dict, fr: str, enc: str, report: LoadReport) -> tuple[str, CameraIntrinsics, Frames]:
        raw = m.raw

        def opt(key: str, default: Any) -> Any:
            return rob.get(key, raw.get(key, default))

        folder = m.resolve(rob["folder"])
        if not folder.is_dir():
            raise ManifestError([Problem(str(folder), f"{fr}.folder", "frame folder not found")])
        found = sorted((int(hit.group(1)), p) for p in folder.iterdir() if (hit := FRAME_RE.match(p.name)))
        if not found:
            raise ManifestError([Problem(str(folder), f"{fr}.folder", "no frame-NNNNNN.color.png|jpg files found")])
        numbers = [n for n, _ in found]
        if len(set(numbers)) != len(numbers):
            raise ManifestError([Problem(str(folder), f"{fr}.folder", "two colour files with the same frame number")])
        colour = [p for _, p in found]
        size = image_size(colour[0])
        if size is None:
            raise ManifestError([Problem(str(colour[0]), f"{fr}.folder", "cannot decode the first colour image")])
        if opt("intrinsics", None) is None:
            raise ManifestError([Problem(str(m.path), f"{fr}.intrinsics", "required (here or at the top level): a 3x3 "
                                         "matrix text file, a camera.yaml or {fx, fy, cx, cy}")])
        where = f"{fr}.intrinsics" if "intrinsics" in rob else "intrinsics"
        K = read_frame_intrinsics(opt("intrinsics", None), m, where, size)
        stems = [p.name.split(".color.")[0] for p in colour]
        probs = file_problems([(p, f"{fr}.folder") for p in colour], "colour image", size)
        depth = None
        if opt("depth", True):
            dpaths = [folder / f"{s}.depth.png" for s in stems]
            present = [p for p in dpaths if p.is_file()]
            if present:  # a folder without any depth file is RGB-only; single missing files are counted
                probs += file_problems([(p, f"{fr}.folder") for p in present], "depth image", size, min_bits=16)
                units = float(opt("depth_units_per_m", 1000.0))
                depth = [DepthFile(p, units, INVALID_DEPTH) if p.is_file() else None for p in dpaths]
                report.count(enc, f"{rob['id']}: frames without a depth file", len(dpaths) - len(present))
        poses = []
        for s in stems:
            p = folder / f"{s}.pose.txt"
            try:
                poses.append(read_pose(p, f"{fr}.folder") if p.is_file() else np.full((4, 4), np.nan))
            except ManifestError as exc:
                probs += exc.problems
            if len(probs) >= 10:
                break
        if probs:
            raise ManifestError(probs)
        stamps = np.array(numbers, dtype=np.float64) / float(opt("rate_hz", 30.0))
        frames = Frames(stamps, colour, np.stack(poses), [f"{folder.name}/{s}" for s in stems], depth)
        return rob["id"], K, apply_slice(frames, rob, str(m.path), fr)

