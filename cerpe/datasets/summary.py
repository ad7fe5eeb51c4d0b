"""Summaries and deep checks of a loaded :class:`~cerpe.scene.Setting` (used by ``cerpe check``).

:func:`summarise` is pure (ground truth and stamps only); :func:`verify_setting`
decodes image and depth files, compares sizes with the intrinsics and checks that
depth is stored with 16 bits and in plausible units.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..scene import Encounter, RobotStream, SceneError, Setting
from .formats import depth_bits
from .manifest import ManifestError, Problem

OVERLAP_THRESHOLD = 0.2
DEPTH_PLAUSIBLE_M = (0.1, 100.0)  # median valid depth of a frame outside this: wrong depth_units_per_m


def summarise(setting: Setting) -> dict:
    """Counts and ground-truth statistics of a setting.

    Returns a dict with ``encounters``, ``robots`` (distinct ids), ``frames``
    (robot-frames), ``steps``, ``pairs`` (ordered pairs x evaluated steps),
    ``pairs_with_gt``, ``sync_max_abs_s`` (stamp sync residual),
    ``index_sync_max_offset_s`` (stamp offset between index-synchronised robots), ``overlap_mean``,
    ``overlap_frac_ge_0_2`` (NaN without ground-truth overlap),
    ``view_angle_min_deg`` / ``view_angle_max_deg`` (NaN without ground truth)
    and ``per_encounter`` rows.
    """
    every = int(setting.meta.get("evaluation_every", 1))
    rows = []
    ids: set[str] = set()
    angles_all: list[float] = []
    overlaps_all: list[float] = []
    for enc in setting.encounters:
        ids.update(enc.robot_ids)
        steps = range(0, enc.n_steps, every)
        pairs = enc.ordered_pairs()
        angles = [enc.gt_viewing_angle(t, i, j) for t in steps for i, j in pairs]
        angles = [a for a in angles if np.isfinite(a)]
        ov = []
        if enc.overlap is not None:
            ov = [enc.overlap[t, i, j] for t in steps for i, j in pairs]
            ov = [v for v in ov if np.isfinite(v)]
        angles_all += angles
        overlaps_all += ov
        rows.append({
            "encounter": enc.name, "robots": ",".join(enc.robot_ids), "steps": enc.n_steps,
            "pairs": len(steps) * len(pairs), "pairs_with_gt": len(angles),
            "overlap_mean": float(np.mean(ov)) if ov else float("nan"),
            "view_angle_max_deg": float(np.degrees(max(angles))) if angles else float("nan"),
        })
    sync = setting.meta.get("load_report", {}).get("sync", {})
    res = [r["max_abs_s"] for enc in sync.values() for r in enc.values() if r.get("mode", "stamp") == "stamp"]
    offs = [r["max_abs_s"] for enc in sync.values() for r in enc.values() if r.get("mode") == "index"]
    return {
        "setting": setting.name,
        "encounters": len(setting.encounters),
        "robots": len(ids),
        "frames": int(sum(enc.n_steps * len(enc.robots) for enc in setting.encounters)),
        "steps": int(sum(enc.n_steps for enc in setting.encounters)),
        "pairs": int(sum(r["pairs"] for r in rows)),
        "pairs_with_gt": int(sum(r["pairs_with_gt"] for r in rows)),
        "sync_max_abs_s": float(max(res)) if res else float("nan"),
        "index_sync_max_offset_s": float(max(offs)) if offs else float("nan"),
        "overlap_mean": float(np.mean(overlaps_all)) if overlaps_all else float("nan"),
        "overlap_frac_ge_0_2": float(np.mean(np.array(overlaps_all) >= OVERLAP_THRESHOLD)) if overlaps_all else float("nan"),
        "view_angle_min_deg": float(np.degrees(min(angles_all))) if angles_all else float("nan"),
        "view_angle_max_deg": float(np.degrees(max(angles_all))) if angles_all else float("nan"),
        "per_encounter": rows,
    }


def _frames_to_check(n: int, max_frames: int | None) -> list[int]:
    if max_frames is None or max_frames >= n:
        return list(range(n))
    return sorted(set(np.linspace(0, n - 1, max_frames).round().astype(int).tolist()))


def ref_file(ref: object) -> Path | None:
    """The file behind an image/depth reference: a path, or a reference object's ``path`` attribute."""
    if isinstance(ref, (str, Path)):
        return Path(ref)
    path = getattr(ref, "path", None)
    return Path(path) if isinstance(path, (str, Path)) else None


def robot_field(enc: Encounter, rid: str) -> str:
    """The manifest field of robot ``rid`` (``encounters[e].robots[r]``) when the adapter recorded it."""
    return str(enc.meta.get("robot_fields", {}).get(rid, f"{enc.name}/{rid}"))


def _depth_units(rob: RobotStream, ref: object) -> float:
    units = getattr(ref, "units_per_m", None)
    return float(units) if units is not None else float(rob.depth_units_per_m)


def verify_setting(setting: Setting, max_frames: int | None = None, progress: bool = True) -> list[Problem]:
    """Decode images and depth maps; check sizes, depth bit depth and depth units.

    Args:
        setting: a loaded setting.
        max_frames: check at most this many frames per robot and encounter
            (evenly spaced, >= 1); None checks every frame.
        progress: show a tqdm bar.

    Returns:
        every problem found (file, field ``<encounter>/<robot>/<frame>``, message). A depth
        image with fewer than 16 bits per value is refused (an 8-bit PNG cannot hold depth);
        a frame whose median valid depth lies outside :data:`DEPTH_PLAUSIBLE_M` after the
        units conversion names the robot's ``depth_units_per_m`` field (once per robot).
    """
    if max_frames is not None and max_frames < 1:
        raise ManifestError(f"frames to check must be >= 1, got {max_frames}", field="--frames")
    probs: list[Problem] = []
    units_reported: set[tuple[str, str]] = set()
    jobs = [(enc, rob, t) for enc in setting.encounters for rob in enc.robots
            for t in _frames_to_check(len(rob), max_frames)]
    for enc, rob, t in tqdm(jobs, desc=f"check {setting.name}", unit="frame", disable=not progress, leave=False):
        ref = rob.images[t]
        path = ref_file(ref)
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
        bits = depth_bits(dpath) if dpath is not None and dpath.is_file() else None
        if bits is not None and bits < 16:
            probs.append(Problem(dfile, where, f"{bits}-bit depth image: depth must be stored with 16 bits "
                                               "(integer units, see depth_units_per_m) or as float (.npy/.exr)"))
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
        lo, hi = DEPTH_PLAUSIBLE_M
        if valid.size and not lo <= float(np.median(valid)) <= hi and (enc.name, rob.robot_id) not in units_reported:
            units_reported.add((enc.name, rob.robot_id))
            units = _depth_units(rob, dref)
            manifest = str(setting.meta.get("manifest", dfile))
            probs.append(Problem(manifest, f"{robot_field(enc, rob.robot_id)}.depth_units_per_m",
                                 f"median depth of {dfile} is {float(np.median(valid)):.4g} m after dividing by "
                                 f"depth_units_per_m={units:g}; expected {lo:g}-{hi:g} m (wrong units?)"))
    return probs
