"""Ground-truth co-visibility of real data from its depth and poses, cached.

Where a dataset has depth and ground-truth poses but no overlap file, the
adapters fill ``Encounter.overlap`` ``[T, N, N]`` with the overlap ratio
``cerpe synth`` uses (:mod:`cerpe.synth.groundtruth`): the fraction of robot a's
valid-depth pixels that, moved into robot b's camera with the ground-truth poses,
land inside b's image, in front of it, and agree with b's depth there. Real
depth and real ground truth are noisy, so the ratio is a slight under-estimate
(a pose error of a few centimetres fails some depth tests); NaN where a robot has
no depth or no ground-truth pose at that step.

The result is cached under ``<cache>/covisibility/<setting>/<encounter>-<key>.npy``
(``<cache>`` = ``$CERPE_CACHE`` or ``build/`` in the checkout; key = hash of the
depth files' names, sizes and times, the poses, the intrinsics and the parameters),
written atomically. The run folders then carry it per step as ``overlap_gt``.
Manifest field ``covisibility: auto`` (default) or ``off``.
"""
from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from ..scene import Encounter, SceneError
from ..synth.groundtruth import ABS_TOL_M, REL_TOL, overlap_ratio
from .manifest import Manifest, Problem, cache_base
from .report import LoadReport

COVISIBILITY_MODES: tuple[str, ...] = ("auto", "off")
STRIDE = 4  # pixel grid of the overlap ratio (a fraction: the stride trades noise for speed)
VERSION = 1  # bump when the computation changes: old cache files are then ignored


def validate(m: Manifest) -> list[Problem]:
    """The manifest's ``covisibility`` field: ``auto`` (default) or ``off``."""
    v = m.raw.get("covisibility", "auto")
    return [] if v in COVISIBILITY_MODES else [
        Problem(str(m.path), "covisibility", f"expected one of {', '.join(COVISIBILITY_MODES)}, got {v!r}")]


def _describe(ref: Any) -> list | None:
    """What identifies a depth reference's content for the cache key; None when unknown (not cached)."""
    if ref is None:
        return ["none"]
    if isinstance(ref, np.ndarray):
        return ["array", hashlib.sha256(np.ascontiguousarray(ref).tobytes()).hexdigest()]
    path = Path(ref) if isinstance(ref, (str, Path)) else getattr(ref, "path", None)
    if path is None:
        return None
    try:
        st = Path(path).stat()
    except OSError:
        return [str(path), "missing"]
    out = [str(path), st.st_size, st.st_mtime_ns]
    if not isinstance(ref, (str, Path)):
        und = getattr(ref, "undistort", None)
        out += [getattr(ref, "units_per_m", None), list(getattr(ref, "invalid", ())), getattr(ref, "size", None),
                getattr(ref, "rot90", 0), None if und is None else [und.K.as_list(), list(und.dist)]]
    return out


def cache_key(enc: Encounter, stride: int = STRIDE) -> str | None:
    """Hash of everything the overlap of ``enc`` depends on; None when a depth reference cannot be identified."""
    h = hashlib.sha256(repr((VERSION, stride, REL_TOL, ABS_TOL_M)).encode())
    for rob in enc.robots:
        h.update(repr((rob.robot_id, rob.intrinsics.as_list(), rob.depth_units_per_m)).encode())
        h.update(np.ascontiguousarray(rob.T_world_cam).tobytes())
        for ref in rob.depth or []:
            d = _describe(ref)
            if d is None:
                return None
            h.update(repr(d).encode())
    return h.hexdigest()[:24]


def compute_overlap(enc: Encounter, stride: int = STRIDE, progress: bool = True) -> np.ndarray:
    """``[T, N, N]`` overlap ratios of every ordered robot pair per step (diagonal 1; NaN where unknown).

    Raises:
        SceneError: a depth file cannot be read (the message names it).
    """
    n = len(enc.robots)
    out = np.full((enc.n_steps, n, n), np.nan)
    bar = tqdm(range(enc.n_steps), desc=f"covisibility {enc.name}", unit="step", leave=False,
               disable=None if progress else True)  # None: only on a terminal, never into a log file
    for t in bar:
        depth = [rob.depth_m(t) if rob.depth is not None and rob.has_gt(t) else None for rob in enc.robots]
        for i, a in enumerate(enc.robots):
            if depth[i] is None:
                continue
            out[t, i, i] = 1.0
            for j, b in enumerate(enc.robots):
                if j != i and depth[j] is not None:
                    out[t, i, j] = overlap_ratio(depth[i], a.intrinsics, a.T_world_cam[t], depth[j], b.intrinsics,
                                                 b.T_world_cam[t], stride)
    return out


def _atomic_save(path: Path, arr: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as fh:
        np.save(fh, arr, allow_pickle=False)
    os.replace(tmp, path)


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name)


def attach(m: Manifest, enc: Encounter, report: LoadReport, progress: bool = True) -> None:
    """Fill ``enc.overlap`` from depth and poses when none is given and every robot has depth.

    Skipped (overlap stays None) with ``covisibility: off``, when a robot has no
    depth, or when no step has ground truth for two robots. A depth file that
    cannot be read becomes a problem in ``report`` naming it.
    """
    if enc.overlap is not None or m.raw.get("covisibility", "auto") == "off":
        return
    if any(rob.depth is None for rob in enc.robots):
        return
    gt = np.array([[rob.has_gt(t) for rob in enc.robots] for t in range(enc.n_steps)])
    if not np.any(gt.sum(axis=1) >= 2):
        return
    key = cache_key(enc)
    path = cache_base() / "covisibility" / _safe(m.name) / f"{_safe(enc.name)}-{key}.npy" if key else None
    if path is not None and path.is_file():
        try:
            ov = np.load(path, allow_pickle=False)
            if ov.shape == (enc.n_steps, len(enc.robots), len(enc.robots)):
                enc.overlap = ov
                return
        except (OSError, ValueError):
            pass  # unreadable cache file: compute again and replace it
    try:
        ov = compute_overlap(enc, progress=progress)
    except SceneError as exc:
        report.add(Problem(str(m.path), f"{enc.name}: covisibility", str(exc)))
        return
    if path is not None:
        _atomic_save(path, ov)
    enc.overlap = ov
