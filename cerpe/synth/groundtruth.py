"""Ground truth between rendered frames: visual-overlap ratio and viewing angle.

Overlap of an ordered pair ``(i, j)``: the fraction of image i's *surface* pixels
(depth > 0) that j sees. Sky is not counted: it has no position to be co-visible. A
pixel's 3D point is back-projected with i's exact depth and re-projected into camera j.
It counts when it lands inside image j in front of it and agrees with j's own depth
there (no occluder in between) within ``abs_tol_m + rel_tol * z_j``. Pixels of i are
sampled on a regular grid with ``stride`` (the ratio is a fraction, so this only trades
noise for speed).
"""
from __future__ import annotations

import numpy as np

from ..geometry import paper_T_ij, viewing_angle
from ..scene import CameraIntrinsics

REL_TOL = 0.02
ABS_TOL_M = 0.02


def backproject(depth_m: np.ndarray, K: CameraIntrinsics, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points ``[M,3]`` of the pixels with depth > 0 on a ``stride`` grid, and their ``(v,u)`` indices."""
    H, W = depth_m.shape
    vv, uu = np.mgrid[0:H:stride, 0:W:stride]
    z = depth_m[vv, uu]
    ok = z > 0
    u, v, z = uu[ok].astype(np.float64), vv[ok].astype(np.float64), z[ok].astype(np.float64)
    pts = np.stack([(u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z], 1)
    return pts, np.stack([vv[ok], uu[ok]], 1)


def reproject_check(pts_ci: np.ndarray, T_cj_ci: np.ndarray, depth_j: np.ndarray, K_j: CameraIntrinsics,
                    rel_tol: float = REL_TOL, abs_tol_m: float = ABS_TOL_M,
                    bilinear: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Move camera-i points into camera j and compare with j's depth there.

    ``bilinear=False`` reads j's depth at the nearest pixel; ``True`` interpolates
    *inverse* depth bilinearly (exact on planes, since 1/z is affine in pixel
    coordinates for a plane) and gives 0 where any of the 4 neighbours has no surface.

    Returns:
        visible ``[M] bool`` (inside j, in front, depth-consistent), ``z_j [M]`` the
        points' depth in j, ``d_j [M]`` j's rendered depth at the projected point
        (0 where outside the image).
    """
    p = pts_ci @ T_cj_ci[:3, :3].T + T_cj_ci[:3, 3]
    z = p[:, 2]
    H, W = depth_j.shape
    with np.errstate(divide="ignore", invalid="ignore"):
        uf = K_j.fx * p[:, 0] / z + K_j.cx
        vf = K_j.fy * p[:, 1] / z + K_j.cy
    u, v = np.rint(uf), np.rint(vf)
    inside = (z > 1e-6) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    d = np.zeros(len(z))
    if not bilinear:
        d[inside] = depth_j[v[inside].astype(int), u[inside].astype(int)]
    else:
        inside &= (uf >= 0) & (uf < W - 1) & (vf >= 0) & (vf < H - 1)
        x0, y0 = np.floor(uf[inside]).astype(int), np.floor(vf[inside]).astype(int)
        ax, ay = uf[inside] - x0, vf[inside] - y0
        q = [depth_j[y0, x0], depth_j[y0, x0 + 1], depth_j[y0 + 1, x0], depth_j[y0 + 1, x0 + 1]]
        ok = np.all([qq > 0 for qq in q], axis=0)
        inv = [np.where(ok, 1.0 / np.where(ok, qq, 1.0), 0.0) for qq in q]
        w = (inv[0] * (1 - ax) * (1 - ay) + inv[1] * ax * (1 - ay) + inv[2] * (1 - ax) * ay + inv[3] * ax * ay)
        d[inside] = np.where(ok, 1.0 / np.where(ok, w, 1.0), 0.0)
    vis = inside & (d > 0) & (np.abs(z - d) <= abs_tol_m + rel_tol * z)
    return vis, z, d


def overlap_ratio(depth_i: np.ndarray, K_i: CameraIntrinsics, T_world_ci: np.ndarray, depth_j: np.ndarray,
                  K_j: CameraIntrinsics, T_world_cj: np.ndarray, stride: int = 4) -> float:
    """Fraction of i's surface pixels visible in j (see module docstring); 0 if i sees no surface."""
    pts, _ = backproject(depth_i, K_i, stride)
    if len(pts) == 0:
        return 0.0
    vis, _, _ = reproject_check(pts, paper_T_ij(T_world_ci, T_world_cj), depth_j, K_j)
    return float(vis.mean())


def overlap_matrix(depths: list[np.ndarray], Ks: list[CameraIntrinsics], T_world_cams: list[np.ndarray],
                   stride: int = 4) -> np.ndarray:
    """``[N,N]`` overlap ratios of every ordered pair (diagonal 1)."""
    n = len(depths)
    out = np.eye(n)
    for i in range(n):
        for j in range(n):
            if i != j:
                out[i, j] = overlap_ratio(depths[i], Ks[i], T_world_cams[i], depths[j], Ks[j], T_world_cams[j], stride)
    return out


def viewing_angle_matrix(T_world_cams: list[np.ndarray]) -> np.ndarray:
    """``[N,N]`` relative viewing angles (radians) = rotation angle of ``T_cj_ci``."""
    n = len(T_world_cams)
    out = np.zeros((n, n))
    for i in range(n):
        for j in range(n):
            if i != j:
                out[i, j] = float(viewing_angle(paper_T_ij(T_world_cams[i], T_world_cams[j])))
    return out


def has_transition(overlap: np.ndarray, high: float = 0.3, low: float = 0.05) -> bool:
    """True when some cross-robot ordered pair rises above ``high`` and falls below ``low``
    at least once over the ``[T,N,N]`` overlap series."""
    T, n, _ = overlap.shape
    for i in range(n):
        for j in range(n):
            if i != j and overlap[:, i, j].max() > high and overlap[:, i, j].min() < low:
                return True
    return False
