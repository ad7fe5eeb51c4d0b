"""Pure helpers of the offline backbone: descriptor matching, rays, triangulation, depths at keypoints.

Conventions: pixels ``(u, v)`` with centres at integers (OpenCV), normalised rays
``(x, y, 1)``, ``T_1_0`` maps camera-0 points into camera 1, depths in metres.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ...scene import CameraIntrinsics
from ..cache import LRUCache
from ..xfeat import XFeatFeatures

# mutual nearest-neighbour matching of XFeat descriptors: a match needs a cosine similarity above
# MIN_COSSIM and Lowe's distance ratio below RATIO both ways
MIN_COSSIM = 0.82
RATIO = 0.95
# a keypoint's depth is unknown when the known pixels of its 3x3 neighbourhood spread by more than
# this fraction of their median (keypoints sit on corners and edges: one pixel off is the background)
DEPTH_EDGE_TOL = 0.2


def match_mnn(desc0: np.ndarray, desc1: np.ndarray, min_cossim: float = MIN_COSSIM,
              ratio: float = RATIO) -> np.ndarray:
    """Mutual nearest-neighbour matches of L2-normalised descriptors.

    Args:
        desc0: ``[N0,D]``; desc1: ``[N1,D]`` (unit rows).
        min_cossim: a match needs cosine similarity above this.
        ratio: Lowe's ratio on distances (best / second best) must be below it
            in both directions (1 disables it).

    Returns:
        ``[M,2] int64`` index pairs ``(i0, i1)``, sorted by ``i0``.

    The similarity matrix is one float32 product; the best and second-best of each row and of
    each matched column come from row/column maxima (``argmax`` along rows, ``max`` along
    columns, the best entries masked for the second): far cheaper than a top-k on both axes,
    which needs a transposed copy of the matrix, and the same values.
    """
    if len(desc0) == 0 or len(desc1) == 0:
        return np.zeros((0, 2), np.int64)
    import torch

    with torch.inference_mode():  # the product as before: the same float32 similarities
        sim = (torch.from_numpy(np.ascontiguousarray(desc0, np.float32)) @ torch.from_numpy(
            np.ascontiguousarray(desc1, np.float32)).T).numpy()
    i0 = np.arange(sim.shape[0])
    nn01 = sim.argmax(axis=1)
    best32 = sim[i0, nn01]
    col_best = sim.max(axis=0)
    mutual = best32 >= col_best[nn01]  # row i0 is the best of its best column
    best = best32.astype(np.float64)
    keep = mutual & (best > min_cossim)
    if ratio < 1.0 and sim.shape[0] >= 2 and sim.shape[1] >= 2:
        # the second best of every row: its best masked; of every matched column: only the
        # mutual entries masked (a column's best is its mutual row's)
        sim[i0, nn01] = -np.inf
        second01 = sim.max(axis=1).astype(np.float64)
        other = ~mutual
        sim[i0[other], nn01[other]] = best32[other]
        second10 = sim.max(axis=0).astype(np.float64)[nn01]
        # distances of unit vectors: d^2 = 2 - 2 cos
        d_best = np.sqrt(np.maximum(2 - 2 * best, 0))
        keep &= d_best < ratio * np.sqrt(np.maximum(2 - 2 * second01, 0))
        keep &= d_best < ratio * np.sqrt(np.maximum(2 - 2 * second10, 0))
    return np.stack([i0[keep], nn01[keep]], axis=1).astype(np.int64)


class PairMatcher:
    """:func:`match_mnn` of two images' features, cached by both images' content keys.

    A pair is matched once, in the order of the content keys, whichever order it is
    asked in; the other order gets the same pairs swapped and sorted by its first
    column. A cache hit therefore equals a recomputation, and no answer depends on
    which passes ran before.
    """

    def __init__(self, min_cossim: float, ratio: float, cache_size: int) -> None:
        self.min_cossim, self.ratio = float(min_cossim), float(ratio)
        self.cache: LRUCache[np.ndarray] = LRUCache(cache_size)
        self.n_computed = 0
        self.n_cached = 0

    def __call__(self, fa: XFeatFeatures, fb: XFeatFeatures) -> np.ndarray:
        """``[M,2] int64`` keypoint index pairs ``(ia, ib)``, sorted by ``ia``."""
        ka, kb = fa.fingerprint, fb.fingerprint
        if not ka or not kb:  # features made without a content key: nothing to cache them by
            self.n_computed += 1
            return match_mnn(fa.descriptors, fb.descriptors, self.min_cossim, self.ratio)
        flip = kb < ka
        key = (kb, ka) if flip else (ka, kb)
        m = self.cache.get(key)
        if m is None:
            first, second = (fb, fa) if flip else (fa, fb)
            m = match_mnn(first.descriptors, second.descriptors, self.min_cossim, self.ratio)
            m.setflags(write=False)
            self.cache.put(key, m)
            self.n_computed += 1
        else:
            self.n_cached += 1
        if flip:
            m = m[:, ::-1]
            m = m[np.argsort(m[:, 0], kind="stable")]
        return m

    def clear(self) -> None:
        self.cache.clear()


def pixels_to_rays(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """``[N,2]`` pixels -> ``[N,3]`` normalised camera rays ``(x, y, 1)``."""
    return np.column_stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))])


def triangulate(rays0: np.ndarray, rays1: np.ndarray, T_1_0: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation of ray pairs ``[N,3]``; ``[N,3]`` points in camera 0
    (NaN/inf for degenerate rays; callers filter)."""
    P0 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P1 = T_1_0[:3, :]
    A = np.stack([
        rays0[:, 0:1] * P0[2] - P0[0], rays0[:, 1:2] * P0[2] - P0[1],
        rays1[:, 0:1] * P1[2] - P1[0], rays1[:, 1:2] * P1[2] - P1[1],
    ], axis=1)  # [N,4,4]
    _, _, Vt = np.linalg.svd(A)
    X = Vt[:, -1, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        return X[:, :3] / X[:, 3:4]


def reprojection_error(X_cam: np.ndarray, uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixel distance between projected camera-frame points ``[N,3]`` and ``uv [N,2]`` (inf if behind)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = X_cam @ K.T
        proj = proj[:, :2] / proj[:, 2:3]
    err = np.linalg.norm(proj - uv, axis=1)
    return np.where(np.isfinite(err), err, np.inf)


def triangulation_angle_deg(X: np.ndarray, c0: np.ndarray, c1: np.ndarray) -> np.ndarray:
    """Angle at each point ``[N,3]`` between the rays to camera centres ``c0`` and ``c1``."""
    a = X - c0
    b = X - c1
    cos = np.sum(a * b, axis=1) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-12)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def pose_to_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``[4,4]`` from a rotation ``[3,3]`` and a translation ``[3]`` (poselib's ``R``, ``t``)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, float)
    T[:3, 3] = np.asarray(t, float).ravel()
    return T


def pinhole_camera(intr: CameraIntrinsics) -> dict[str, Any]:
    """poselib's camera dict of a pinhole camera."""
    return {"model": "PINHOLE", "width": int(intr.width), "height": int(intr.height),
            "params": [float(intr.fx), float(intr.fy), float(intr.cx), float(intr.cy)]}


def splat_depth(uv: np.ndarray, depth: np.ndarray, conf: np.ndarray, hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Sparse ``[H,W]`` depth and confidence maps from point depths at pixels ``uv``.

    The nearest point wins where two fall on one pixel. Non-finite or
    non-positive depths are dropped; everything else stays 0.
    """
    H, W = hw
    D = np.zeros((H, W), np.float32)
    C = np.zeros((H, W), np.float32)
    if len(uv) == 0:
        return D, C
    u = np.round(uv[:, 0]).astype(np.int64)
    v = np.round(uv[:, 1]).astype(np.int64)
    ok = (u >= 0) & (u < W) & (v >= 0) & (v < H) & np.isfinite(depth) & (depth > 0) & np.isfinite(conf)
    u, v, d, c = u[ok], v[ok], depth[ok], conf[ok]
    order = np.argsort(-d)  # far first, so the nearest is written last and wins
    D[v[order], u[order]] = d[order]
    C[v[order], u[order]] = np.maximum(c[order], 0)
    return D, C


def map_index(x: np.ndarray, n_map: int, n_img: int) -> np.ndarray:
    """Index along one axis of a ``n_map``-pixel map under image coordinate ``x`` of an
    ``n_img``-pixel image (nearest neighbour on pixel centres, clipped to the map)."""
    return np.clip(np.floor((x + 0.5) * n_map / n_img).astype(np.int64), 0, n_map - 1)


def keypoint_depths(uv: np.ndarray, depth_m: np.ndarray, image_hw: tuple[int, int],
                    edge_tol: float = DEPTH_EDGE_TOL, min_valid: int = 5) -> np.ndarray:
    """Metric depth at keypoints ``uv [N,2]`` (image pixels) from a depth map of any size.

    Each keypoint takes the median of the known pixels (> 0, finite) of its 3x3
    neighbourhood in the map (nearest neighbour on pixel centres), which also damps
    per-pixel noise; 0 (unknown) when fewer than ``min_valid`` of the 9 are known or
    they spread by more than ``edge_tol`` of that median: keypoints sit on corners and
    edges, where one pixel off is the background.

    Returns:
        ``[N] float64`` depths in metres, 0 where unknown.
    """
    D = np.asarray(depth_m)
    if D.ndim != 2 or D.size == 0 or len(uv) == 0:
        return np.zeros(len(uv))
    H, W = image_hw
    hd, wd = D.shape
    u = map_index(uv[:, 0], wd, W)
    v = map_index(uv[:, 1], hd, H)
    # the 3x3 windows gathered from the map as it is (no float64 copy of the whole map): NaN
    # outside it and where the depth is unknown
    flat = np.ascontiguousarray(D).reshape(-1)
    cols = []
    for dv in (-1, 0, 1):
        for du in (-1, 0, 1):
            vv, uu = v + dv, u + du
            inside = (vv >= 0) & (vv < hd) & (uu >= 0) & (uu < wd)
            vals = flat[np.clip(vv, 0, hd - 1) * wd + np.clip(uu, 0, wd - 1)].astype(np.float64)
            cols.append(np.where(inside & np.isfinite(vals) & (vals > 0), vals, np.nan))
    win = np.stack(cols, axis=1)  # [N,9]
    n = np.sum(np.isfinite(win), axis=1)
    out = np.zeros(len(uv))
    ok = n >= min_valid
    if ok.any():
        # the median, max and min of the known values of each row from one sort (NaN sorts last):
        # the values np.nanmedian / nanmax / nanmin give, several times faster
        w = np.sort(win[ok], axis=1)
        nv, r = n[ok], np.arange(int(ok.sum()))
        z = (w[r, (nv - 1) // 2] + w[r, nv // 2]) / 2
        spread = (w[r, nv - 1] - w[r, 0]) / z
        out[np.flatnonzero(ok)] = np.where(spread <= edge_tol, z, 0.0)
    return out


