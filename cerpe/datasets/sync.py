"""Time association shared by the adapters: nearest stamps, pose lookup, multi-robot sync.

All functions are pure numpy on stamps in seconds (:func:`check_window` validates a manifest value).
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from ..geometry import interpolate_pose
from .manifest import Problem, is_number


def nearest(query_s: np.ndarray, stamps_s: np.ndarray, tol_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Index of the nearest stamp for every query, -1 where none is within ``tol_s``.

    Args:
        query_s: ``[Q]`` query stamps.
        stamps_s: ``[N]`` sorted stamps (N may be 0).
        tol_s: largest accepted ``|dt|`` (inclusive).

    Returns:
        ``(idx [Q] int, dt [Q] float)`` with ``dt = stamps_s[idx] - query_s`` (NaN where -1).
    """
    query_s = np.asarray(query_s, dtype=np.float64)
    stamps_s = np.asarray(stamps_s, dtype=np.float64)
    idx = np.full(len(query_s), -1, dtype=np.int64)
    dt = np.full(len(query_s), np.nan)
    if len(stamps_s) == 0 or len(query_s) == 0:
        return idx, dt
    hi = np.clip(np.searchsorted(stamps_s, query_s), 0, len(stamps_s) - 1)
    lo = np.clip(hi - 1, 0, len(stamps_s) - 1)
    pick = np.where(np.abs(stamps_s[lo] - query_s) <= np.abs(stamps_s[hi] - query_s), lo, hi)
    d = stamps_s[pick] - query_s
    ok = np.abs(d) <= tol_s + 1e-12
    idx[ok] = pick[ok]
    dt[ok] = d[ok]
    return idx, dt


def poses_at(
    query_s: np.ndarray,
    stamps_s: np.ndarray,
    T_world_body: np.ndarray,
    tol_s: float,
    interpolate: bool = False,
    max_gap_s: float = 0.1,
) -> np.ndarray:
    """Poses at the query stamps; rows of NaN where none is close enough.

    With ``interpolate``, a query between two samples at most ``max_gap_s`` apart
    gets the SLERP/linear interpolation (:func:`cerpe.geometry.interpolate_pose`);
    otherwise (and as a fallback) the nearest sample within ``tol_s`` is used.

    Returns:
        ``[Q,4,4]``.
    """
    query_s = np.asarray(query_s, dtype=np.float64)
    out = np.full((len(query_s), 4, 4), np.nan)
    idx, _ = nearest(query_s, stamps_s, tol_s)
    for q, k in enumerate(idx):
        if k >= 0:
            out[q] = T_world_body[k]
    if interpolate and len(stamps_s) >= 2:
        hi = np.searchsorted(stamps_s, query_s, side="left")
        for q, h in enumerate(hi):
            if h <= 0 or h >= len(stamps_s):
                continue
            t0, t1 = stamps_s[h - 1], stamps_s[h]
            if t1 - t0 > max_gap_s:
                continue
            a = (query_s[q] - t0) / (t1 - t0)
            out[q] = interpolate_pose(T_world_body[h - 1], T_world_body[h], float(a))
    return out


def check_window(v: Any, f: str, field: str) -> list[Problem]:
    """Problems of a manifest ``window_s`` value (``[start, end]``, numbers or null; see :func:`window_mask`)."""
    if v is None:
        return []
    if not (isinstance(v, list) and len(v) == 2 and all(x is None or is_number(x) for x in v)):
        return [Problem(f, field, f"expected [start_s, end_s] (numbers or null), got {v!r}")]
    a, b = v
    if a is not None and b is not None and (float(a) >= 0) == (float(b) >= 0) and float(b) <= float(a):
        return [Problem(f, field, f"end {b} must be after start {a}")]
    return []


def window_mask(stamps_s: np.ndarray, window: Sequence[float | None] | None) -> np.ndarray:
    """Boolean mask of stamps inside ``[start, end]`` seconds.

    Times are relative to the first stamp; a negative value counts back from the
    last stamp (``[-8, null]`` = the last 8 s); ``null`` leaves that end open.
    """
    stamps_s = np.asarray(stamps_s, dtype=np.float64)
    if window is None or len(stamps_s) == 0:
        return np.ones(len(stamps_s), dtype=bool)
    t0, t1 = stamps_s[0], stamps_s[-1]

    def absolute(v: float | None, default: float) -> float:
        if v is None:
            return default
        return t1 + float(v) if float(v) < 0 else t0 + float(v)

    lo, hi = absolute(window[0], t0), absolute(window[1], t1)
    return (stamps_s >= lo - 1e-9) & (stamps_s <= hi + 1e-9)


def synchronise(
    stamps: Sequence[np.ndarray], tol_s: float, mode: str = "stamp"
) -> tuple[list[np.ndarray], list[np.ndarray], int]:
    """Associate the frames of several robots into common steps.

    ``stamp``: robot 0 is the reference; each of its frames becomes a step when
    every other robot has a frame within ``tol_s`` (nearest); a partner frame is
    used at most once (the closest reference frame keeps it). ``index``: step k
    is frame k of every robot, truncated to the shortest robot (for one
    sequence split into robots; stamps then differ by design).

    Returns:
        ``(indices, residuals_s, dropped)``: per robot the ``[T]`` frame indices and
        ``[T]`` stamp differences to robot 0, and the number of reference frames
        (``stamp``) or trailing frames of longer robots (``index``) dropped.
    """
    if mode == "index":
        T = min(len(s) for s in stamps)
        idx = [np.arange(T) for _ in stamps]
        res = [np.asarray(s[:T]) - np.asarray(stamps[0][:T]) for s in stamps]
        dropped = sum(len(s) - T for s in stamps)
        return idx, res, dropped
    ref = np.asarray(stamps[0], dtype=np.float64)
    keep = np.ones(len(ref), dtype=bool)
    matches = []
    for s in stamps[1:]:
        idx, dt = nearest(ref, s, tol_s)
        # one partner frame per step: the reference frame closest to it keeps it
        best: dict[int, int] = {}
        for r, k in enumerate(idx):
            if k < 0:
                continue
            if k not in best or abs(dt[r]) < abs(dt[best[k]]):
                best[k] = r
        owned = np.zeros(len(ref), dtype=bool)
        owned[list(best.values())] = True
        keep &= owned
        matches.append((idx, dt))
    steps = np.flatnonzero(keep)
    indices = [steps]
    residuals = [np.zeros(len(steps))]
    for idx, dt in matches:
        indices.append(idx[steps])
        residuals.append(dt[steps])
    return indices, residuals, int(len(ref) - len(steps))


def associate(first_s: np.ndarray, second_s: np.ndarray, tol_s: float,
              offset_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Pair two stamp lists the way TUM RGB-D's ``associate.py`` does.

    Every pair with ``|first - (second + offset)| < tol_s`` is a candidate; candidates
    are taken in order of increasing difference, each stamp used at most once.

    Returns:
        ``(i_first, i_second)`` index arrays of the pairs, sorted by ``i_first``.
    """
    a = np.asarray(first_s, dtype=np.float64)
    b = np.asarray(second_s, dtype=np.float64) + offset_s
    order = np.argsort(b, kind="stable")
    bs = b[order]
    cand: list[tuple[float, int, int]] = []
    for i, s in enumerate(a):
        lo, hi = np.searchsorted(bs, s - tol_s, "left"), np.searchsorted(bs, s + tol_s, "right")
        cand += [(abs(s - bs[k]), i, int(order[k])) for k in range(lo, hi) if abs(s - bs[k]) < tol_s]
    cand.sort()
    used_a: set[int] = set()
    used_b: set[int] = set()
    pairs = []
    for _, i, j in cand:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    pairs.sort()
    return (np.array([i for i, _ in pairs], dtype=np.int64), np.array([j for _, j in pairs], dtype=np.int64))
