"""The checks every loaded setting goes through, for ``cerpe check`` and ``cerpe run`` alike.

:func:`load_setting <cerpe.datasets.load_setting>` runs :func:`check_setting` after the
adapter, whatever the adapter. ``cerpe check`` decodes every frame (or ``--frames N``); a
run decodes :data:`SAMPLE_FRAMES` evenly spaced frames per robot and encounter. So a
dataset ``cerpe check`` refuses is refused when a run loads it too. Checked:

* ids that name files of a run (encounter names, robot ids): letters, digits, ``_ . -``,
  not starting with a dot, whichever adapter made them;
* intrinsics against the image size (principal point inside the image);
* every depth PNG's header: fewer than 16 bits cannot hold depth (26 bytes read per file);
* decoded frames: image size against the intrinsics, depth size against the image;
* a frame's median valid depth outside :data:`DEPTH_PLAUSIBLE_M` (an error naming the robot's
  ``depth_units_per_m``), and a depth map without any valid pixel (counted);
* a robot whose median depth lies outside :data:`DEPTH_TYPICAL_M` or its depth sensor's range
  (a warning with the figure, naming ``depth_units_per_m``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..scene import Encounter, RobotStream, SceneError, Setting
from .formats import depth_bits, intrinsics_problem, png_header
from .manifest import ManifestError, Problem, unsafe_id
from .report import LoadReport

SAMPLE_FRAMES = 3  # frames per robot and encounter decoded when a setting is loaded to be run
SAMPLE_MAX = 240  # at most this many sampled frames per setting (pair lists are thousands of 1-frame robots)
DEPTH_PLAUSIBLE_M = (0.1, 100.0)  # a frame's median valid depth outside this: wrong depth_units_per_m (error)
DEPTH_TYPICAL_M = (0.5, 20.0)  # a robot's median depth outside this: probably wrong units (warning)
MAX_FILE_PROBLEMS = 5  # per robot, then "... and N more"
NO_VALID_DEPTH = "depth maps without any valid pixel (no metric scale from them)"


SAMPLE = "sample"  # check_setting's default: SAMPLE_FRAMES per robot and encounter, at most SAMPLE_MAX


def check_setting(setting: Setting, report: LoadReport, frames: int | str | None = SAMPLE,
                  progress: bool = False) -> None:
    """Every check of the module doc; problems, counts and warnings go to ``report``.

    Args:
        frames: frames decoded per robot and encounter (evenly spaced): :data:`SAMPLE` (a run's
            sample), an integer, None for every frame, 0 for none (ids, intrinsics and depth
            headers are checked all the same).
    """
    report.extend(id_problems(setting))
    report.extend(intrinsics_problems(setting))
    bad_depth = depth_header_problems(setting)
    report.extend(bad_depth)
    if frames == 0:
        return
    sample = frames == SAMPLE
    report.extend(verify_setting(setting, SAMPLE_FRAMES if sample else frames, progress, report,
                                 skip={p.file for p in bad_depth}, max_total=SAMPLE_MAX if sample else None))


def ref_file(ref: object) -> Path | None:
    """The file behind an image/depth reference: a path, or a reference object's ``path`` attribute."""
    if isinstance(ref, (str, Path)):
        return Path(ref)
    path = getattr(ref, "path", None)
    return Path(path) if isinstance(path, (str, Path)) else None


def robot_field(enc: Encounter, rid: str) -> str:
    """The manifest field of robot ``rid`` (``encounters[e].robots[r]``) when the adapter recorded it."""
    return str(enc.meta.get("robot_fields", {}).get(rid, f"{enc.name}/{rid}"))


def _manifest(setting: Setting) -> str:
    return str(setting.meta.get("manifest", setting.name))


def id_problems(setting: Setting) -> list[Problem]:
    """Encounter names and robot ids that cannot name files (:func:`~cerpe.datasets.manifest.unsafe_id`)."""
    f, probs = _manifest(setting), []
    for enc in setting.encounters:
        why = unsafe_id(enc.name, "encounter name")
        if why:
            probs.append(Problem(f, enc.name, why))
        for rob in enc.robots:
            why = unsafe_id(rob.robot_id, "robot id")
            if why:
                probs.append(Problem(f, f"{robot_field(enc, rob.robot_id)}.id", why))
    return probs


def intrinsics_problems(setting: Setting) -> list[Problem]:
    """Robots whose intrinsics cannot describe their images (once per robot field)."""
    f, probs, seen = _manifest(setting), [], set()
    for enc in setting.encounters:
        for rob in enc.robots:
            field = f"{robot_field(enc, rob.robot_id)}.intrinsics"
            why = intrinsics_problem(rob.intrinsics)
            if why and field not in seen:
                seen.add(field)
                probs.append(Problem(f, field, why))
    return probs


def depth_header_problems(setting: Setting) -> list[Problem]:
    """Depth PNGs with fewer than 16 bits per value (PNG headers only; other formats when decoded)."""
    probs = []
    for enc in setting.encounters:
        for rob in enc.robots:
            bad = []
            for t, ref in enumerate(rob.depth or []):
                path = ref_file(ref) if ref is not None else None
                hdr = png_header(path) if path is not None and path.suffix.lower() == ".png" else None
                if hdr is not None and hdr[2] < 16:
                    bad.append(Problem(str(path), f"{enc.name}/{rob.robot_id}/{rob.frame_ids[t]}", _few_bits(hdr[2])))
            probs += bad[:MAX_FILE_PROBLEMS]
            if len(bad) > MAX_FILE_PROBLEMS:
                probs.append(Problem(_manifest(setting), f"{robot_field(enc, rob.robot_id)}.depth",
                                     f"... and {len(bad) - MAX_FILE_PROBLEMS} more depth images with too few bits"))
    return probs


def _few_bits(bits: int) -> str:
    return (f"{bits}-bit depth image: depth must be stored with 16 bits (integer units, see depth_units_per_m) "
            "or as float (.npy/.exr)")


def _frames_to_check(n: int, max_frames: int | None) -> list[int]:
    if max_frames is None or max_frames >= n:
        return list(range(n))
    return sorted(set(np.linspace(0, n - 1, max_frames).round().astype(int).tolist()))


def _depth_units(rob: RobotStream, ref: object) -> float:
    units = getattr(ref, "units_per_m", None)
    return float(units) if units is not None else float(rob.depth_units_per_m)


def _typical_range(setting: Setting) -> tuple[float, float, str]:
    """``(lo, hi, what)``: where a robot's median depth should lie, :data:`DEPTH_TYPICAL_M`; with a
    depth *sensor* (``metric_depth: sensor``) the far end is the farthest it measures (``max_m`` of its
    ``metric_depth_options``): half a frame beyond it would be lost."""
    lo, hi = DEPTH_TYPICAL_M
    if setting.metric_depth == "sensor":
        from ..depthsim import SensorDepthSim

        opts = setting.metric_depth_options or {}
        lo = max(lo, float(opts.get("min_m", SensorDepthSim.min_m)))
        hi = float(opts.get("max_m", SensorDepthSim.max_m))
        return lo, hi, f"{lo:g}-{hi:g} m (the far end: the depth sensor's max_m)"
    return lo, hi, f"the usual {lo:g}-{hi:g} m of a robot's camera"


def verify_setting(setting: Setting, max_frames: int | None = None, progress: bool = True,
                   report: LoadReport | None = None, skip: set[str] = frozenset(),
                   max_total: int | None = None) -> list[Problem]:
    """Decode images and depth maps; check sizes, depth bit depth and depth units.

    Args:
        setting: a loaded setting.
        max_frames: check at most this many frames per robot and encounter
            (evenly spaced, >= 1); None checks every frame.
        progress: show a tqdm bar.
        report: where depth maps without a valid pixel are counted and implausible
            median depths warned about (None: neither).
        skip: depth files already refused (not decoded again).
        max_total: decode at most this many frames in all (evenly spread over the jobs).

    Returns:
        every problem found (file, field ``<encounter>/<robot>/<frame>``, message). A frame
        whose median valid depth lies outside :data:`DEPTH_PLAUSIBLE_M` after the units
        conversion names the robot's ``depth_units_per_m`` field (once per robot).
    """
    if max_frames is not None and max_frames < 1:
        raise ManifestError(f"frames to check must be >= 1, got {max_frames}", field="--frames")
    probs: list[Problem] = []
    units_reported: set[tuple[str, str]] = set()
    jobs = [(enc, rob, t) for enc in setting.encounters for rob in enc.robots
            for t in _frames_to_check(len(rob), max_frames)]
    if max_total is not None and len(jobs) > max_total:
        jobs = [jobs[k] for k in sorted(set(np.linspace(0, len(jobs) - 1, max_total).round().astype(int)))]
    medians: dict[tuple[str, str], list[float]] = {}
    manifest = _manifest(setting)
    for enc, rob, t in tqdm(jobs, desc=f"check {setting.name}", unit="frame", disable=not progress, leave=False):
        path = ref_file(rob.images[t])
        file = str(path) if path is not None else "<in memory>"
        where = f"{enc.name}/{rob.robot_id}/{rob.frame_ids[t]}"
        try:
            img = rob.image(t)
        except SceneError as exc:
            probs.append(Problem(file, where, str(exc)))
            continue
        h, w = img.shape[:2]
        K = rob.intrinsics
        if (w, h) != (K.width, K.height):
            probs.append(Problem(file, where, f"image is {w}x{h} but the intrinsics say {K.width}x{K.height}"))
        if rob.depth is None or rob.depth[t] is None:
            continue
        dref = rob.depth[t]
        dpath = ref_file(dref)
        dfile = str(dpath) if dpath is not None else "<depth callable>"
        if dfile in skip:
            continue
        bits = depth_bits(dpath) if dpath is not None and dpath.is_file() and dpath.suffix.lower() != ".png" else None
        if bits is not None and bits < 16:
            probs.append(Problem(dfile, where, _few_bits(bits)))
            continue
        try:
            d = rob.depth_m(t)
        except SceneError as exc:
            probs.append(Problem(dfile, where, str(exc)))
            continue
        if d is None:
            continue
        if d.shape != (h, w):
            probs.append(Problem(dfile, where, f"depth is {d.shape[1]}x{d.shape[0]} but the image is {w}x{h}"))
        valid = d[d > 0]
        if not valid.size:
            if report is not None:
                report.count(enc.name, f"{rob.robot_id}: {NO_VALID_DEPTH}")
            continue
        med = float(np.median(valid))
        medians.setdefault((enc.name, rob.robot_id), []).append(med)
        lo, hi = DEPTH_PLAUSIBLE_M
        if not lo <= med <= hi and (enc.name, rob.robot_id) not in units_reported:
            units_reported.add((enc.name, rob.robot_id))
            probs.append(Problem(manifest, f"{robot_field(enc, rob.robot_id)}.depth_units_per_m",
                                 f"median depth of {dfile} is {med:.4g} m after dividing by "
                                 f"depth_units_per_m={_depth_units(rob, dref):g}; expected {lo:g}-{hi:g} m (wrong units?)"))
    if report is not None:
        _warn_atypical(setting, medians, units_reported, report)
    return probs


def _warn_atypical(setting: Setting, medians: dict[tuple[str, str], list[float]],
                   refused: set[tuple[str, str]], report: LoadReport) -> None:
    """A warning per robot whose median depth (over its decoded frames) lies outside :func:`_typical_range`."""
    lo, hi, what = _typical_range(setting)
    for enc in setting.encounters:
        for rob in enc.robots:
            key = (enc.name, rob.robot_id)
            if key in refused or key not in medians:
                continue
            med = float(np.median(medians[key]))
            if lo < med < hi:
                continue
            units = _depth_units(rob, next((d for d in rob.depth or [] if d is not None), None))
            report.warn(Problem(_manifest(setting), f"{robot_field(enc, rob.robot_id)}.depth_units_per_m",
                                f"robot {rob.robot_id}: median depth {med:.3g} m over {len(medians[key])} decoded "
                                f"frame(s) after dividing by depth_units_per_m={units:g}, not strictly inside {what}: "
                                "are the units right?"))
