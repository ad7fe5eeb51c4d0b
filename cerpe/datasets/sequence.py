"""Robots cut from recorded sequences, and the encounters they form (``tum-rgbd``, ``frames``).

Most relative-pose evaluations without a multi-robot recording build "robots" from
one or two sequences of a scene: one sequence split in two, two sequences of one
room (TUM fr1_desk and fr1_desk2), a sequence and its reverse. A robot entry may
therefore take a slice of its sequence::

    frames: [0, 300]        # positions in the sequence's frame list, end exclusive;
                            #   negative counts from the end, null leaves it open
    window_s: [0.0, 8.0]    # seconds from the first stamp (negative: from the last)
    stride: 2               # every 2nd frame of the slice
    reversed: true          # played backwards

applied in that order (``frames``, ``window_s``, ``stride``, ``reversed``). A
reversed robot's stamps are mirrored (``s' = s_first + s_last - s``) so that they
still increase; its ``frame_ids`` keep the original names. Robots of one
encounter are synchronised by index (default: step k = k-th frame of every
robot, the shortest robot decides) or by stamp (``sync: stamp``, for streams
recorded at the same time; nearest frame within ``sync_tolerance_s``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence as Seq

import numpy as np

from ..scene import CameraIntrinsics, Encounter, RobotStream, SceneError
from . import covisibility
from .manifest import (Manifest, ManifestError, Problem, is_number, mapping_problems, not_a_mapping, type_name,
                       unsafe_id)
from .report import LoadReport
from .sync import check_window, synchronise, window_mask

SLICE_FIELDS: tuple[str, ...] = ("frames", "window_s", "stride", "reversed")
SYNC_MODES: tuple[str, ...] = ("index", "stamp")
ENCOUNTER_FIELDS: tuple[str, ...] = ("name", "sync", "robots")


@dataclass
class Frames:
    """A robot's frames (all lists/arrays of length ``N``), before or after slicing.

    ``T_world_cam`` rows are NaN where the ground truth is unknown; ``depth`` is
    None for RGB-only data.
    """

    stamps_s: np.ndarray
    images: list
    T_world_cam: np.ndarray
    frame_ids: list[str]
    depth: list | None = None

    def __len__(self) -> int:
        return len(self.stamps_s)

    def take(self, idx: Seq[int]) -> "Frames":
        idx = [int(k) for k in idx]
        return Frames(self.stamps_s[idx], [self.images[k] for k in idx], self.T_world_cam[idx],
                      [self.frame_ids[k] for k in idx], None if self.depth is None else [self.depth[k] for k in idx])


def validate_slice(rob: dict, f: str, fr: str) -> list[Problem]:
    """Problems of a robot's slice fields (no file access)."""
    probs = check_window(rob.get("window_s"), f, f"{fr}.window_s")
    rng = rob.get("frames")
    if rng is not None and not (isinstance(rng, list) and len(rng) == 2
                                and all(x is None or (isinstance(x, int) and not isinstance(x, bool)) for x in rng)):
        probs.append(Problem(f, f"{fr}.frames", f"expected [start, end] (integers or null, end exclusive), got {rng!r}"))
    stride = rob.get("stride", 1)
    if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
        probs.append(Problem(f, f"{fr}.stride", f"expected an integer >= 1, got {stride!r}"))
    if not isinstance(rob.get("reversed", False), bool):
        probs.append(Problem(f, f"{fr}.reversed", f"expected true or false, got {rob.get('reversed')!r}"))
    return probs


def apply_slice(frames: Frames, rob: dict, f: str, fr: str) -> Frames:
    """The robot's slice of ``frames`` (see module doc); raises when nothing is left."""
    idx = np.arange(len(frames))
    a, b = rob.get("frames") or (None, None)
    idx = idx[slice(a, b)]
    if rob.get("window_s") is not None:
        idx = idx[window_mask(frames.stamps_s[idx], rob["window_s"])]
    idx = idx[:: int(rob.get("stride", 1))]
    if len(idx) == 0:
        raise ManifestError([Problem(f, fr, f"the slice (frames {rob.get('frames')}, window_s {rob.get('window_s')}) "
                                            f"of {len(frames)} frames is empty")])
    out = frames.take(idx)
    if rob.get("reversed", False):
        out = out.take(range(len(out) - 1, -1, -1))
        out.stamps_s = out.stamps_s[-1] + out.stamps_s[0] - out.stamps_s
    return out


def _unique(value: Any, seen: set[str], f: str, field: str, what: str) -> list[Problem]:
    """A required, unique id that names files (:func:`~cerpe.datasets.manifest.unsafe_id`)."""
    if not isinstance(value, str) or not value:
        return [Problem(f, field, f"required: a non-empty string, got {type_name(value)}")]
    why = unsafe_id(value, what)
    if why:
        return [Problem(f, field, why)]
    if value in seen:
        return [Problem(f, field, f"duplicate {what} {value!r}")]
    seen.add(value)
    return []


def _mapping(obj: Any, f: str, field: str, known: Seq[str], probs: list[Problem]) -> bool:
    """Adds ``obj``'s unknown keys (or "not a mapping") to ``probs``; False when it is not a mapping."""
    unknown = mapping_problems(obj, f, field, known)
    if unknown is None:
        probs.append(not_a_mapping(obj, f, field))
        return False
    probs.extend(unknown)
    return True


def validate_encounter_list(m: Manifest, encounter_fields: Seq[str], robot_fields: Seq[str], sync_modes: Seq[str],
                            sync_default: str, check_encounter: Callable[[dict, str, str], list[Problem]],
                            check_robot: Callable[[dict, str, str], list[Problem]]) -> list[Problem]:
    """Structure of an ``encounters`` list of robots (no file access), every problem.

    Checks mappings, unknown fields, unique encounter names, ``sync``, at least 2
    robots with unique ids; ``check_encounter(enc, file, field)`` and
    ``check_robot(rob, file, field)`` add the adapter's own checks.
    """
    f = str(m.path)
    encs = m.encounters
    if not isinstance(encs, list) or not encs:
        got = "an empty list" if isinstance(encs, list) else type_name(encs)
        return [Problem(f, "encounters", f"expected a non-empty list of encounters, got {got}")]
    probs: list[Problem] = []
    names: set[str] = set()
    for e, enc in enumerate(encs):
        fe = f"encounters[{e}]"
        if not _mapping(enc, f, fe, encounter_fields, probs):
            continue
        probs += _unique(enc.get("name"), names, f, f"{fe}.name", "encounter name")
        if enc.get("sync", sync_default) not in sync_modes:
            probs.append(Problem(f, f"{fe}.sync", f"expected one of {', '.join(sync_modes)}, got {enc.get('sync')!r}"))
        probs += check_encounter(enc, f, fe)
        robots = enc.get("robots")
        if not isinstance(robots, list) or len(robots) < 2:
            n = len(robots) if isinstance(robots, list) else type_name(robots)
            probs.append(Problem(f, f"{fe}.robots", f"expected a list of at least 2 robots, got {n}"))
            continue
        ids: set[str] = set()
        for r, rob in enumerate(robots):
            fr = f"{fe}.robots[{r}]"
            if not _mapping(rob, f, fr, robot_fields, probs):
                continue
            probs += _unique(rob.get("id"), ids, f, f"{fr}.id", "robot id (in this encounter)")
            probs += check_robot(rob, f, fr)
    return probs


def validate_encounters(m: Manifest, robot_fields: Seq[str], required: Seq[str],
                        check_robot: Callable[[dict, str, str], list[Problem]]) -> list[Problem]:
    """:func:`validate_encounter_list` for sliced robots (``sync: index`` by default, slice fields accepted)."""
    def robot(rob: dict, f: str, fr: str) -> list[Problem]:
        probs = [Problem(f, f"{fr}.{k}", f"required: a string, got {type_name(rob.get(k))}")
                 for k in required if not isinstance(rob.get(k), str) or not rob.get(k)]
        return probs + validate_slice(rob, f, fr) + check_robot(rob, f, fr)

    return validate_encounter_list(m, ENCOUNTER_FIELDS, tuple(robot_fields) + SLICE_FIELDS, SYNC_MODES, "index",
                                   lambda enc, f, fe: [], robot)


def load_encounters(m: Manifest, report: LoadReport,
                    robot: Callable[[dict, str, str], tuple[str, CameraIntrinsics, Frames]]) -> list[Encounter]:
    """Every encounter of ``m``: ``robot(rob, field, encounter_name)`` reads one robot (raising
    :class:`ManifestError`), then :func:`assemble_encounter`; all problems go to ``report``."""
    encounters = []
    for e, enc in enumerate(m.encounters):
        robots = []
        for r, rob in enumerate(enc["robots"]):
            try:
                robots.append(robot(rob, f"encounters[{e}].robots[{r}]", enc["name"]))
            except ManifestError as exc:
                report.extend(exc.problems)
        if len(robots) == len(enc["robots"]):
            got = assemble_encounter(m, e, enc, robots, report)
            if got is not None:
                encounters.append(got)
    report.raise_if_problems()
    return encounters


def positive_number(obj: dict, key: str, f: str, field: str) -> list[Problem]:
    """A problem when ``obj[key]`` is present and not a positive number."""
    if key in obj and (not is_number(obj[key]) or float(obj[key]) <= 0):
        return [Problem(f, f"{field}.{key}" if field else key, f"expected a positive number, got {obj[key]!r}")]
    return []


def synchronise_robots(m: Manifest, fe: str, name: str, stamps: list[np.ndarray], mode: str,
                       report: LoadReport) -> tuple[list[np.ndarray], list[np.ndarray]] | None:
    """:func:`~cerpe.datasets.sync.synchronise` for an encounter: counts what it dropped, resets
    ``report.sync[name]``; None (with the problem in ``report``) when no common step remains."""
    idx, res, dropped = synchronise(stamps, m.sync_tolerance_s, mode)
    if len(idx[0]) == 0:
        report.add(Problem(str(m.path), f"{fe}.robots", f"no common steps: no frames of the robots lie within "
                                                         f"sync_tolerance_s={m.sync_tolerance_s} of each other"))
        return None
    report.count(name, "reference frames without partner frames within sync_tolerance_s (dropped)"
                 if mode == "stamp" else "frames beyond the shortest robot (dropped)", dropped)
    report.sync[name] = {}
    return idx, res


def assemble_encounter(m: Manifest, e: int, enc: dict, robots: list[tuple[str, CameraIntrinsics, Frames]],
                       report: LoadReport, meta: dict[str, Any] | None = None) -> Encounter | None:
    """Synchronise sliced robots into an :class:`Encounter`, count what was dropped, add co-visibility.

    Returns None (with the problem in ``report``) when no common step remains.
    """
    fe = f"encounters[{e}]"
    name = enc["name"]
    mode = enc.get("sync", "index")
    got = synchronise_robots(m, fe, name, [fr.stamps_s for _, _, fr in robots], mode, report)
    if got is None:
        return None
    idx, res = got
    streams = []
    for (rid, K, fr), ix, r in zip(robots, idx, res):
        fr = fr.take(ix)
        report.count(name, f"{rid}: frames without ground-truth pose",
                     int(np.sum(~np.all(np.isfinite(fr.T_world_cam), axis=(1, 2)))))
        report.sync[name][rid] = {"max_abs_s": float(np.max(np.abs(r))), "mean_abs_s": float(np.mean(np.abs(r))),
                                  "mode": mode}
        try:
            streams.append(RobotStream(robot_id=rid, intrinsics=K, stamps_s=fr.stamps_s, images=fr.images,
                                       T_world_cam=fr.T_world_cam, depth=fr.depth, frame_ids=fr.frame_ids))
        except SceneError as exc:
            report.add(Problem(str(m.path), f"{fe}.robots", str(exc)))
            return None
    try:
        out = Encounter(name=name, robots=streams, meta={
            "sync": mode, "manifest": str(m.path),
            "robot_fields": {rid: f"{fe}.robots[{r}]" for r, (rid, _, _) in enumerate(robots)}, **(meta or {})})
    except SceneError as exc:
        report.add(Problem(str(m.path), fe, str(exc)))
        return None
    covisibility.attach(m, out, report)
    return out
