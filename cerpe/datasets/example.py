"""``example`` adapter: a complete, small template for writing your own (KITTI-odometry style).

Copy this file to start a new adapter (see ``datasets_manifest/README.md``,
"Adding an adapter"). It reads the KITTI odometry layout::

    <data_root>/sequences/<seq>/image_0/000000.png ...   # one camera, frames numbered from 0
    <data_root>/sequences/<seq>/times.txt                # one stamp (s) per frame
    <data_root>/sequences/<seq>/calib.txt                # "P0: 12 numbers" (3x4 projection, row-major)
    <data_root>/poses/<seq>.txt                          # per frame 12 numbers: 3x4 T_world_cam, row-major

(KITTI's pose files are camera 0's poses, hence ``image_0`` / ``P0`` by default.)

and builds encounters from frame ranges of sequences (e.g. one sequence split
into two "robots", as KITTI has one car per sequence)::

    encounters:
      - name: kitti-00-a
        robots:
          - {id: first, sequence: "00", frames: [0, 50]}     # frames [start, end) of that sequence
          - {id: second, sequence: "00", frames: [100, 150]}
    camera: image_0       # optional top-level field: image folder / projection row (P0)

Robots are synchronised by index (step k = k-th frame of each range): KITTI
sequences were recorded at different times, so their stamps do not correspond.
The four methods below are all an adapter needs: ``validate`` (structure only,
every problem), ``load`` (files -> :class:`cerpe.scene.Setting`, problems into
the report, degradations counted).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..geometry import GeometryError, check_se3
from ..scene import CameraIntrinsics, Encounter, RobotStream, SceneError, Setting
from .formats import image_size
from .manifest import Manifest, ManifestError, Problem, type_name
from .report import LoadReport


def read_kitti_poses(path: Path, field: str) -> np.ndarray:
    """``[N,4,4]`` camera-to-world poses from KITTI's 12-numbers-per-line file; errors name the line."""
    if not path.is_file():
        raise ManifestError([Problem(str(path), field, "pose file not found")])
    poses, probs = [], []
    for k, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if not line.strip():
            continue
        try:
            vals = np.array([float(x) for x in line.split()])
        except ValueError:
            probs.append(Problem(str(path), f"{field} line {k}", "not a number"))
            continue
        if vals.size != 12:
            probs.append(Problem(str(path), f"{field} line {k}", f"expected 12 numbers (3x4 row-major), got {vals.size}"))
            continue
        T = np.vstack([vals.reshape(3, 4), [0, 0, 0, 1]])
        try:
            poses.append(check_se3(T, f"line {k}", atol=1e-3))
        except GeometryError as exc:
            probs.append(Problem(str(path), f"{field} line {k}", str(exc)))
    if probs:
        raise ManifestError(probs)
    if not poses:
        raise ManifestError([Problem(str(path), field, "no poses")])
    return np.stack(poses)


def read_kitti_calib(path: Path, row: str, field: str) -> np.ndarray:
    """``[3,4]`` projection matrix ``P<n>`` from ``calib.txt``."""
    if not path.is_file():
        raise ManifestError([Problem(str(path), field, "calib.txt not found")])
    for line in path.read_text(encoding="utf-8").splitlines():
        key, _, rest = line.partition(":")
        if key.strip() == row:
            try:
                return np.array([float(x) for x in rest.split()]).reshape(3, 4)
            except ValueError:
                break
    raise ManifestError([Problem(str(path), field, f"no valid '{row}: 12 numbers' line")])


class KittiStyleAdapter:
    """Template adapter: KITTI-odometry-style sequences split into robots."""

    name = "example"
    top_level_fields: tuple[str, ...] = ("camera",)

    def validate(self, manifest: Manifest) -> list[Problem]:
        f = str(manifest.path)
        encs = manifest.encounters
        if not isinstance(encs, list) or not encs:
            return [Problem(f, "encounters", f"expected a non-empty list, got {type_name(encs)}")]
        probs = []
        for e, enc in enumerate(encs):
            fe = f"encounters[{e}]"
            if not isinstance(enc, dict) or not isinstance(enc.get("name"), str):
                probs.append(Problem(f, fe, "expected a mapping with a string 'name'"))
                continue
            robots = enc.get("robots")
            if not isinstance(robots, list) or len(robots) < 2:
                probs.append(Problem(f, f"{fe}.robots", "expected a list of at least 2 robots"))
                continue
            for r, rob in enumerate(robots):
                fr = f"{fe}.robots[{r}]"
                if not isinstance(rob, dict) or not isinstance(rob.get("id"), str):
                    probs.append(Problem(f, fr, "expected a mapping with a string 'id'"))
                    continue
                if not isinstance(rob.get("sequence"), str):
                    probs.append(Problem(f, f"{fr}.sequence", f"expected a string like \"00\", got {rob.get('sequence')!r}"))
                fr_ = rob.get("frames")
                if fr_ is not None and not (isinstance(fr_, list) and len(fr_) == 2 and all(isinstance(x, int) for x in fr_)
                                            and 0 <= fr_[0] < fr_[1]):
                    probs.append(Problem(f, f"{fr}.frames", f"expected [start, end) with 0 <= start < end, got {fr_!r}"))
        return probs

    def load(self, manifest: Manifest, report: LoadReport) -> Setting:
        cam = str(manifest.raw.get("camera", "image_0"))
        encounters = []
        for e, enc in enumerate(manifest.encounters):
            streams = []
            for r, rob in enumerate(enc["robots"]):
                fr = f"encounters[{e}].robots[{r}]"
                try:
                    streams.append(self._robot(manifest, rob, cam, fr, report, enc["name"]))
                except ManifestError as exc:
                    report.extend(exc.problems)
            if len(streams) != len(enc["robots"]):
                continue
            T = min(len(s) for s in streams)  # index sync: truncate to the shortest range
            report.count(enc["name"], "frames beyond the shortest robot (dropped)", sum(len(s) - T for s in streams))
            streams = [RobotStream(s.robot_id, s.intrinsics, s.stamps_s[:T], list(s.images[:T]), s.T_world_cam[:T],
                                   frame_ids=list(s.frame_ids[:T])) for s in streams]
            try:
                encounters.append(Encounter(name=enc["name"], robots=streams, meta={"sync": "index"}))
            except SceneError as exc:
                report.add(manifest.problem(f"encounters[{e}]", str(exc)))
        report.raise_if_problems()
        return Setting(name=manifest.name, encounters=encounters, metric_depth=manifest.metric_depth)

    def _robot(self, m: Manifest, rob: dict, cam: str, fr: str, report: LoadReport, enc: str) -> RobotStream:
        seq = m.resolve(Path("sequences") / rob["sequence"])
        images = sorted((seq / cam).glob("*.png")) if (seq / cam).is_dir() else []
        if not images:
            raise ManifestError([Problem(str(seq / cam), f"{fr}.sequence", "no .png images found")])
        times_file = seq / "times.txt"
        try:
            stamps = np.loadtxt(times_file, ndmin=1)
        except (OSError, ValueError) as exc:
            raise ManifestError([Problem(str(times_file), f"{fr}.sequence", f"cannot read stamps: {exc}")]) from None
        poses = read_kitti_poses(m.resolve(Path("poses") / f"{rob['sequence']}.txt"), f"{fr}.sequence")
        n = len(images)
        if len(stamps) != n:
            raise ManifestError([Problem(str(times_file), f"{fr}.sequence", f"{len(stamps)} stamps for {n} images")])
        if len(poses) < n:  # KITTI test sequences have no poses at all: NaN ground truth, counted
            report.count(enc, f"{rob['id']}: frames without ground-truth pose", n - len(poses))
            poses = np.concatenate([poses, np.full((n - len(poses), 4, 4), np.nan)])
        a, b = rob.get("frames") or [0, n]
        if b > n:
            raise ManifestError([Problem(str(m.path), f"{fr}.frames", f"end {b} is beyond the {n} frames of the sequence")])
        P = read_kitti_calib(seq / "calib.txt", "P" + cam.rsplit("_", 1)[-1], f"{fr}.sequence")
        size = image_size(images[a])
        if size is None:
            raise ManifestError([Problem(str(images[a]), f"{fr}.sequence", "cannot decode image")])
        K = CameraIntrinsics(fx=P[0, 0], fy=P[1, 1], cx=P[0, 2], cy=P[1, 2], width=size[0], height=size[1])
        return RobotStream(robot_id=rob["id"], intrinsics=K, stamps_s=stamps[a:b], images=images[a:b],
                           T_world_cam=poses[a:b], frame_ids=[f"{rob['sequence']}/{p.stem}" for p in images[a:b]])
