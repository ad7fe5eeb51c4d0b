"""``mocap`` adapter: per-robot image folders with motion-capture (or any) ground truth.

This is also the layout ``cerpe synth`` writes. Manifest ``encounters`` entries::

    - name: lab-s0                     # unique in the manifest
      sync: stamp                      # stamp (nearest within sync_tolerance_s) | index
      window_s: [0.0, 5.0]             # optional; relative to robot 0's first stamp (negative: from its end)
      overlap: lab-s0/overlap.npy      # optional [T0, N, N]; T0 = robot 0's image count before any window
      robots:
        - id: r0
          images: lab-s0/r0/rgb        # folder of <stamp>.png|jpg, or a "stamp path" list file
          image_stamp_units: s         # s | ms | us | ns (names/lines of the image list)
          trajectory: lab-s0/r0/groundtruth.txt   # optional (no ground truth without it)
          trajectory_format: tum       # tum | euroc | csv
          gt_tolerance_s: 0.02         # nearest pose within this; else NaN ground truth (counted)
          interpolate: false           # true: SLERP between samples <= interpolate_max_gap_s apart
          interpolate_max_gap_s: 0.1
          intrinsics: lab-s0/r0/camera.yaml
          T_body_cam: identity         # camera pose in the body frame: T_world_cam = T_world_body @ T_body_cam
          depth: lab-s0/r0/depth       # optional folder, same stems as the images
          depth_units_per_m: 1000
          window_s: [0.0, 8.0]         # optional per-robot window (relative to this robot's stamps)

Paths are relative to the manifest's ``data_root``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..scene import CameraIntrinsics, Encounter, RobotStream, SceneError, Setting
from . import covisibility
from .formats import (NONFINITE_ROWS, STAMP_UNITS, TRAJECTORY_FORMATS, Trajectory, find_depth_files, ground_truth_problems,
                      list_images, parse_transform, read_camera, read_trajectory)
from .imageref import DepthFile, ImageFile, Undistortion, undistortion
from .manifest import Manifest, ManifestError, Problem, type_name
from .report import LoadReport
from .sequence import synchronise_robots, validate_encounter_list
from .sync import check_window, poses_at, window_mask

ENCOUNTER_FIELDS = ("name", "sync", "window_s", "overlap", "robots", "meta")
ROBOT_FIELDS = (
    "id", "images", "image_stamp_units", "trajectory", "trajectory_format", "gt_tolerance_s", "interpolate",
    "interpolate_max_gap_s", "intrinsics", "T_body_cam", "depth", "depth_units_per_m", "window_s",
)
SYNC_MODES = ("stamp", "index")


def _check_encounter(enc: dict, f: str, fe: str) -> list[Problem]:
    probs = check_window(enc.get("window_s"), f, f"{fe}.window_s")
    if "overlap" in enc and not isinstance(enc["overlap"], str):
        probs.append(Problem(f, f"{fe}.overlap", f"expected a path to a .npy file, got {type_name(enc['overlap'])}"))
    return probs


def _check_robot(rob: dict, f: str, fr: str) -> list[Problem]:
    probs = []
    for k in ("images", "intrinsics"):
        if not isinstance(rob.get(k), str) or not rob.get(k):
            probs.append(Problem(f, f"{fr}.{k}", f"required: a path string, got {type_name(rob.get(k))}"))
    for k in ("trajectory", "depth"):
        if k in rob and not isinstance(rob[k], str):
            probs.append(Problem(f, f"{fr}.{k}", f"expected a path string, got {type_name(rob[k])}"))
    if rob.get("trajectory_format", "tum") not in TRAJECTORY_FORMATS:
        probs.append(Problem(f, f"{fr}.trajectory_format",
                             f"expected one of {', '.join(TRAJECTORY_FORMATS)}, got {rob.get('trajectory_format')!r}"))
    if rob.get("image_stamp_units", "s") not in STAMP_UNITS:
        probs.append(Problem(f, f"{fr}.image_stamp_units",
                             f"expected one of {', '.join(STAMP_UNITS)}, got {rob.get('image_stamp_units')!r}"))
    probs += ground_truth_problems(rob, f, fr, ("gt_tolerance_s", "interpolate_max_gap_s", "depth_units_per_m"))
    return probs + check_window(rob.get("window_s"), f, f"{fr}.window_s")


def validate_encounters(m: Manifest) -> list[Problem]:
    """Structure of a mocap ``encounters`` list (types, required fields, unique names); no file access."""
    return validate_encounter_list(m, ENCOUNTER_FIELDS, ROBOT_FIELDS, SYNC_MODES, "stamp", _check_encounter, _check_robot)


@dataclass
class _RobotData:
    """One robot's files read, before synchronisation."""

    rid: str
    stamps_s: np.ndarray
    images: list[Path]
    orig_idx: np.ndarray  # index into the full image list (before windows)
    n_total: int  # images in the full list
    intrinsics: CameraIntrinsics  # of the images as loaded (undistorted when the camera file has distortion)
    undistort: Undistortion | None
    T_body_cam: np.ndarray
    traj: Trajectory | None
    depth: list[Path | None] | None
    depth_units_per_m: float
    gt_tol_s: float
    interpolate: bool
    max_gap_s: float


def _read_robot(m: Manifest, rob: dict, fr: str, enc_name: str, report: LoadReport) -> _RobotData | None:
    probs: list[Problem] = []
    rid = rob["id"]

    def attempt(fn, *a):
        try:
            return fn(*a)
        except ManifestError as exc:
            probs.extend(exc.problems)
            return None

    listed = attempt(list_images, m.resolve(rob["images"]), f"{fr}.images", rob.get("image_stamp_units", "s"))
    cam = attempt(read_camera, m.resolve(rob["intrinsics"]), f"{fr}.intrinsics")
    und = undistortion(*cam) if cam is not None else None  # distorted images are undistorted once, on load
    intr = None if cam is None else (und.intrinsics if und is not None else cam[0])
    T_bc = attempt(parse_transform, rob.get("T_body_cam", "identity"), f"{fr}.T_body_cam", str(m.path), m.resolve)
    traj = None
    if rob.get("trajectory"):
        traj = attempt(read_trajectory, m.resolve(rob["trajectory"]), rob.get("trajectory_format", "tum"), f"{fr}.trajectory")
    depth_dir = m.resolve(rob["depth"]) if rob.get("depth") else None
    if depth_dir is not None and not depth_dir.is_dir():
        probs.append(Problem(str(depth_dir), f"{fr}.depth", "depth folder not found"))
    if listed is not None:
        missing = [p for p in listed[1] if not p.is_file()]
        for p in missing[:5]:
            probs.append(Problem(str(p), f"{fr}.images", "image file not found"))
        if len(missing) > 5:
            probs.append(Problem(str(m.resolve(rob["images"])), f"{fr}.images", f"... and {len(missing) - 5} more missing image files"))
    if probs or listed is None or intr is None or T_bc is None:
        report.extend(probs)
        return None
    stamps, images = listed
    orig = np.arange(len(stamps))
    keep = window_mask(stamps, rob.get("window_s"))
    if not keep.any():
        report.add(Problem(str(m.path), f"{fr}.window_s", f"no image of robot {rid} inside the window {rob.get('window_s')}"))
        return None
    stamps, orig = stamps[keep], orig[keep]
    images = [images[k] for k in orig]
    if traj is not None:
        report.count(enc_name, f"{rid}: {NONFINITE_ROWS}", traj.n_nan_rows)
    depth = None
    if depth_dir is not None:
        depth = find_depth_files(depth_dir, [p.stem for p in images])
        report.count(enc_name, f"{rid}: frames without a depth file", sum(d is None for d in depth))
        if und is not None and any(d is not None and d.suffix.lower() != ".png" for d in depth):
            report.extend([Problem(str(depth_dir), f"{fr}.depth", "a distorted camera needs 16-bit PNG depth "
                                   "(undistorted with the images); convert .npy/.exr depth or undistort it first")])
            return None
    return _RobotData(
        rid=rid, stamps_s=stamps, images=images, orig_idx=orig, n_total=len(listed[0]), intrinsics=intr,
        undistort=und, T_body_cam=T_bc, traj=traj,
        depth=depth, depth_units_per_m=float(rob.get("depth_units_per_m", 1.0)),
        gt_tol_s=float(rob.get("gt_tolerance_s", 0.02)), interpolate=bool(rob.get("interpolate", False)),
        max_gap_s=float(rob.get("interpolate_max_gap_s", 0.1)),
    )


def _load_overlap(m: Manifest, enc: dict, fe: str, n_ref_frames: int, n_robots: int,
                  ref_rows: np.ndarray, report: LoadReport) -> np.ndarray | None:
    path = m.resolve(enc["overlap"])
    f, field = str(path), f"{fe}.overlap"
    if not path.is_file():
        report.add(Problem(f, field, "overlap file not found"))
        return None
    try:
        ov = np.load(path, allow_pickle=False)
    except Exception as exc:  # truncated or not a .npy
        report.add(Problem(f, field, f"cannot read .npy: {exc}"))
        return None
    if ov.shape != (n_ref_frames, n_robots, n_robots):
        report.add(Problem(f, field, f"shape {ov.shape}, expected ({n_ref_frames}, {n_robots}, {n_robots}) "
                                     "= (robot 0's image count before windows, robots, robots)"))
        return None
    ov = ov.astype(np.float64)
    fin = ov[np.isfinite(ov)]
    if fin.size and (fin.min() < -1e-6 or fin.max() > 1 + 1e-6):
        report.add(Problem(f, field, f"overlap ratios must lie in [0, 1], found [{fin.min():.3g}, {fin.max():.3g}]"))
        return None
    return ov[ref_rows]


def load_encounter(m: Manifest, e: int, enc: dict, report: LoadReport) -> Encounter | None:
    """Read, window and synchronise one encounter; None (with problems in ``report``) on failure."""
    fe = f"encounters[{e}]"
    name = enc["name"]
    datas = [_read_robot(m, rob, f"{fe}.robots[{r}]", name, report) for r, rob in enumerate(enc["robots"])]
    if any(d is None for d in datas):
        return None
    if enc.get("window_s") is not None:
        ref = datas[0].stamps_s
        keep0 = window_mask(ref, enc["window_s"])
        if not keep0.any():
            report.add(Problem(str(m.path), f"{fe}.window_s", f"no image of robot {datas[0].rid} inside the window"))
            return None
        lo, hi = ref[keep0][0], ref[keep0][-1]
        for d in datas:
            k = (d.stamps_s >= lo - m.sync_tolerance_s) & (d.stamps_s <= hi + m.sync_tolerance_s)
            d.stamps_s, d.orig_idx = d.stamps_s[k], d.orig_idx[k]
            d.images = [p for p, kk in zip(d.images, k) if kk]
            if d.depth is not None:
                d.depth = [p for p, kk in zip(d.depth, k) if kk]
    mode = enc.get("sync", "stamp")
    got = synchronise_robots(m, fe, name, [d.stamps_s for d in datas], mode, report)
    if got is None:
        return None
    idx, res = got
    T = len(idx[0])
    streams = []
    for d, ix, r in zip(datas, idx, res):
        stamps = d.stamps_s[ix]
        if d.traj is not None:
            T_wb = poses_at(stamps, d.traj.stamps_s, d.traj.T_world_body, d.gt_tol_s, d.interpolate, d.max_gap_s)
        else:
            T_wb = np.full((T, 4, 4), np.nan)
        T_wc = T_wb @ d.T_body_cam
        n_nan = int(np.sum(~np.all(np.isfinite(T_wc), axis=(1, 2))))
        report.count(name, f"{d.rid}: frames without ground-truth pose", n_nan)
        report.sync[name][d.rid] = {"max_abs_s": float(np.max(np.abs(r))) if len(r) else 0.0,
                                    "mean_abs_s": float(np.mean(np.abs(r))) if len(r) else 0.0, "mode": mode}
        try:
            images, depth, units = [d.images[k] for k in ix], None, d.depth_units_per_m
            if d.depth is not None:
                depth = [d.depth[k] for k in ix]
            if d.undistort is not None:  # read, then undistorted with the same maps (depth: nearest neighbour)
                images = [ImageFile(p, d.undistort) for p in images]
                if depth is not None:
                    depth, units = [None if p is None else DepthFile(p, units, (), d.undistort) for p in depth], 1.0
            streams.append(RobotStream(
                robot_id=d.rid, intrinsics=d.intrinsics, stamps_s=stamps, images=images,
                T_world_cam=T_wc, depth=depth, depth_units_per_m=units, frame_ids=[d.images[k].stem for k in ix],
            ))
        except SceneError as exc:
            report.add(Problem(str(m.path), f"{fe}.robots", str(exc)))
            return None
    overlap = None
    if enc.get("overlap"):
        overlap = _load_overlap(m, enc, fe, datas[0].n_total, len(datas), datas[0].orig_idx[idx[0]], report)
        if overlap is None:
            return None
    try:
        out = Encounter(name=name, robots=streams, overlap=overlap,
                         meta={"sync": mode, "manifest": str(m.path),
                               "robot_fields": {d.rid: f"{fe}.robots[{r}]" for r, d in enumerate(datas)},
                               **(enc.get("meta") or {})})
    except SceneError as exc:
        report.add(Problem(str(m.path), fe, str(exc)))
        return None
    covisibility.attach(m, out, report)  # no overlap file: from depth + poses where there is depth
    return out


class MocapAdapter:
    """Image folders + trajectories (TUM / EuRoC / CSV) + camera.yaml per robot."""

    name = "mocap"
    top_level_fields: tuple[str, ...] = ("covisibility",)

    def validate(self, manifest: Manifest) -> list[Problem]:
        return covisibility.validate(manifest) + validate_encounters(manifest)

    def load(self, manifest: Manifest, report: LoadReport) -> Setting:
        encounters = []
        for e, enc in enumerate(manifest.encounters):
            got = load_encounter(manifest, e, enc, report)
            if got is not None:
                encounters.append(got)
        report.raise_if_problems()
        return Setting(name=manifest.name, encounters=encounters, metric_depth=manifest.metric_depth,
                       meta={"manifest": str(manifest.path), "adapter": self.name})
