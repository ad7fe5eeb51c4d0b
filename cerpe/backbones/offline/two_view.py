"""Image-only reconstruction: essential matrices, triangulation, and the merge into a metric pass.

Without a depth prior, the current view and the first candidate with enough
essential-matrix inliers and parallax define the pass (unit: their baseline); their
inliers are triangulated. A view too few 2D-3D correspondences place falls back to
its essential matrix with the current view, scaled by the points both see (or by the
current view's own depth prior). When the depth-anchored pass left out a view that
the image-only one placed, :func:`merge_image_only` adds it at the metric scale, if
the two agree on the views both placed.
"""
from __future__ import annotations

from collections import Counter
from typing import Sequence

import numpy as np

from ...geometry import se3_inverse
from .context import FIVE_POINT_SAMPLE, Pass, Recon, bounded
from .matching import (keypoint_depths, pixels_to_rays, pose_to_T, reprojection_error, triangulate,
                       triangulation_angle_deg)

MIN_MATCHES = 30  # fewer matches between two views: few-matches
EPIPOLAR_PX = 1.0  # essential-matrix RANSAC threshold (Sampson error), px
MIN_INLIER_RATIO = 0.2  # an essential matrix needs this fraction of the matches as inliers
# the reference pair's parallax: that quantile of its triangulation angles below the minimum -> no-parallax
MIN_PARALLAX_DEG = 0.5
PARALLAX_QUANTILE = 0.8
# triangulated points kept: reprojecting within MAX_REPROJ_PX in both views, rays at least MIN_POINT_ANGLE_DEG apart
MAX_REPROJ_PX = 3.0
MIN_POINT_ANGLE_DEG = 0.2
MIN_SCALE_POINTS = 8  # shared points a two-view placement needs for its scale
# agreement the image-only views need to join a metric pass (:func:`merge_image_only`)
MERGE_MAX_ROT_PX = 3.0
MERGE_MAX_DIR_DEG = 10.0
MERGE_MAX_RATIO_SPREAD = 1.25
MERGE_MIN_BASELINE_M = 0.05


def relative_pose(ransac: dict[str, float], uv0: np.ndarray, uv1: np.ndarray, cam0: dict, cam1: dict,
                  min_inliers: int, min_matches: int = MIN_MATCHES, epipolar_px: float = EPIPOLAR_PX,
                  min_inlier_ratio: float = MIN_INLIER_RATIO) -> tuple[np.ndarray | None, np.ndarray, str]:
    """Essential-matrix RANSAC (poselib, 5-point): ``T_1_0`` with unit translation, the
    inlier mask and a reason (``""``, ``few-matches``, ``few-inliers``).

    Needs ``min_matches`` matches, then ``min_inliers`` inliers within ``epipolar_px`` (Sampson)
    that are at least ``min_inlier_ratio`` of them."""
    import poselib

    if len(uv0) < min_matches:
        return None, np.zeros(len(uv0), bool), "few-matches"
    need = max(int(min_inliers), int(np.ceil(min_inlier_ratio * len(uv0))))
    ransac = {**bounded(ransac, need, len(uv0), FIVE_POINT_SAMPLE), "max_epipolar_error": float(epipolar_px)}
    pose, info = poselib.estimate_relative_pose(uv0.astype(np.float64), uv1.astype(np.float64), cam0, cam1,
                                                ransac, {})
    inl = np.asarray(info["inliers"], bool)
    if inl.sum() < min_inliers or inl.mean() < min_inlier_ratio:
        return None, inl, "few-inliers"
    T = pose_to_T(pose.R, pose.t)
    if not np.all(np.isfinite(T)) or np.linalg.norm(T[:3, 3]) < 1e-9:
        return None, inl, "few-inliers"
    T[:3, 3] /= np.linalg.norm(T[:3, 3])
    return T, inl, ""


def pair_pose(p: Pass, a: int, b: int) -> tuple[np.ndarray | None, np.ndarray, str]:
    """:func:`relative_pose` of views ``a`` and ``b`` over their matches, once per pass."""
    if (a, b) not in p.relative:
        m = p.m(a, b)
        p.relative[(a, b)] = relative_pose(p.ransac(), p.feats[a].keypoints[m[:, 0]], p.feats[b].keypoints[m[:, 1]],
                                           p.cams[a], p.cams[b], p.conf.min_inliers)
    return p.relative[(a, b)]


def triangulate_pair(uv0: np.ndarray, uv1: np.ndarray, K0: np.ndarray, K1: np.ndarray,
                     T_1_0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points in camera 0, a keep mask (in front of both, reprojecting within :data:`MAX_REPROJ_PX`,
    angle at least :data:`MIN_POINT_ANGLE_DEG`), mean reprojection error (px), angle (deg)."""
    X = triangulate(pixels_to_rays(uv0, K0), pixels_to_rays(uv1, K1), T_1_0)
    X1 = X @ T_1_0[:3, :3].T + T_1_0[:3, 3]
    e0 = reprojection_error(X, uv0, K0)
    e1 = reprojection_error(X1, uv1, K1)
    ang = triangulation_angle_deg(X, np.zeros(3), se3_inverse(T_1_0)[:3, 3])
    keep = (np.all(np.isfinite(X), axis=1) & (X[:, 2] > 0) & (X1[:, 2] > 0)
            & (e0 < MAX_REPROJ_PX) & (e1 < MAX_REPROJ_PX))
    return X, keep & (ang >= MIN_POINT_ANGLE_DEG), 0.5 * (e0 + e1), ang


def bootstrap(p: Pass, anchor: int, cands: Sequence[int]) -> tuple[Recon | None, dict[int, str]]:
    """Points from ``anchor`` and the first candidate with a good essential matrix and
    parallax (the :data:`PARALLAX_QUANTILE` of the triangulation angles: forward motion has
    none at the focus of expansion, pure rotation none anywhere). Returns the
    reconstruction (frame: ``anchor``'s camera) and a reason per candidate that failed."""
    why: dict[int, str] = {}
    for s in cands:
        if p.low_tex[s]:
            why[s] = "low-texture"
            continue
        m = p.m(anchor, s)
        uva, uvs = p.feats[anchor].keypoints[m[:, 0]], p.feats[s].keypoints[m[:, 1]]
        T_s_a, inl, reason = pair_pose(p, anchor, s)
        if T_s_a is None:
            why[s] = reason
            continue
        X, keep, _, ang = triangulate_pair(uva[inl], uvs[inl], p.Ks[anchor], p.Ks[s], T_s_a)
        parallax = float(np.quantile(ang, PARALLAX_QUANTILE))
        if parallax < MIN_PARALLAX_DEG:
            why[s] = "no-parallax"
            continue
        if keep.sum() < p.conf.min_inliers:
            why[s] = "few-3d-points"
            continue
        mi = m[inl][keep]
        ids = np.arange(len(mi))
        return Recon(X=X[keep], T={anchor: np.eye(4), s: se3_inverse(T_s_a)},
                     obs={anchor: (ids, mi[:, 0]), s: (ids, mi[:, 1])}, pair=(anchor, s)), why
    return None, why


def two_view_with_scale(p: Pass, s: int, rec: Recon) -> str:
    """Place view ``s`` by its essential matrix with view 0 (placed), the translation scaled
    by the depths of the points both see. Writes ``rec.T[s]`` (and its observations);
    returns ``""`` or a reason."""
    m0s = p.m(0, s)
    uv0 = p.feats[0].keypoints[m0s[:, 0]]
    uvs = p.feats[s].keypoints[m0s[:, 1]]
    T_s_0, inl, why = pair_pose(p, 0, s)
    if T_s_0 is None:
        return why
    cur_to_pt = rec.kp_to_pt(0, p.feats[0].n)
    shared = inl & (cur_to_pt[m0s[:, 0]] >= 0)
    if shared.sum() < MIN_SCALE_POINTS:
        return two_view_prior_scale(p, s, rec, m0s, inl, T_s_0)
    X_unit, keep, _, _ = triangulate_pair(uv0[shared], uvs[shared], p.Ks[0], p.Ks[s], T_s_0)
    pt = cur_to_pt[m0s[shared, 0]]
    if keep.sum() < MIN_SCALE_POINTS:
        return "no-parallax"
    T_0_f = se3_inverse(rec.T[0])
    X0 = rec.X[pt[keep]] @ T_0_f[:3, :3].T + T_0_f[:3, 3]  # shared points in camera 0
    scale = float(np.median(X0[:, 2] / X_unit[keep, 2]))
    if not np.isfinite(scale) or scale <= 0:
        return "few-3d-points"
    T_s_0 = T_s_0.copy()
    T_s_0[:3, 3] *= scale
    rec.T[s] = rec.T[0] @ se3_inverse(T_s_0)
    rec.obs[s] = (pt[keep], m0s[shared, 1][keep])
    return ""


def two_view_prior_scale(p: Pass, s: int, rec: Recon, m0s: np.ndarray, inl: np.ndarray,
                         T_s_0: np.ndarray) -> str:
    """Scale of a unit two-view pose with view 0 from view 0's own depth prior at the
    triangulated inliers (too few points shared with the reconstruction); metric passes only."""
    if p.views[0].depth_m is None or not rec.metric:
        return "few-3d-points"
    uv0 = p.feats[0].keypoints[m0s[inl, 0]]
    uvs = p.feats[s].keypoints[m0s[inl, 1]]
    X_unit, keep, _, _ = triangulate_pair(uv0, uvs, p.Ks[0], p.Ks[s], T_s_0)
    z = keypoint_depths(uv0, p.views[0].depth_m, p.feats[0].image_hw)
    keep &= z > 0
    if keep.sum() < MIN_SCALE_POINTS:
        return "few-3d-points"
    scale = float(np.median(z[keep] / X_unit[keep, 2]))
    if not np.isfinite(scale) or scale <= 0:
        return "few-3d-points"
    T = T_s_0.copy()
    T[:3, 3] *= scale
    rec.T[s] = rec.T[0] @ se3_inverse(T)
    return ""


def merge_image_only(rec: Recon, rec_i: Recon, focal_px: float, counts: Counter) -> list[int]:
    """Add to the metric ``rec`` the views that only the image-only ``rec_i`` placed.

    Both frames are the current camera's. ``rec_i``'s unit is the median ratio of the
    translations of the views both placed (those at least :data:`MERGE_MIN_BASELINE_M` away);
    nothing is added unless the two agree on those views: rotations within
    :data:`MERGE_MAX_ROT_PX` pixels at the focal length ``focal_px`` (what two-view geometry
    resolves depends on it), translation directions within :data:`MERGE_MAX_DIR_DEG`, ratios
    within a factor :data:`MERGE_MAX_RATIO_SPREAD`. Each added view brings its points of
    ``rec_i``, scaled. Refusals are counted in ``counts`` (``merge-refused:<why>``).
    Returns the added view indices."""
    extra = [s for s in rec_i.T if s not in rec.T]
    common = [s for s in rec.T if s in rec_i.T and s != 0]
    ratios = []
    for s in common:
        Tm, Ti = rec.T[s], rec_i.T[s]
        cos = (np.trace(Tm[:3, :3].T @ Ti[:3, :3]) - 1.0) / 2.0
        if np.arccos(np.clip(cos, -1.0, 1.0)) * focal_px > MERGE_MAX_ROT_PX:
            counts["merge-refused:rotation"] += 1
            return []
        tm, ti = Tm[:3, 3], Ti[:3, 3]
        nm, ni = float(np.linalg.norm(tm)), float(np.linalg.norm(ti))
        if nm < MERGE_MIN_BASELINE_M or ni <= 0:
            continue
        if np.degrees(np.arccos(np.clip(tm @ ti / (nm * ni), -1.0, 1.0))) > MERGE_MAX_DIR_DEG:
            counts["merge-refused:direction"] += 1
            return []
        ratios.append(nm / ni)
    if not extra:
        return []
    if not ratios or max(ratios) > MERGE_MAX_RATIO_SPREAD * min(ratios):
        counts["merge-refused:" + ("no-baseline" if not ratios else "scale")] += 1
        return []
    scale = float(np.median(ratios))
    for s in extra:
        T = rec_i.T[s].copy()
        T[:3, 3] *= scale
        ids, kp = rec_i.obs[s]
        new = np.arange(len(rec.X), len(rec.X) + len(ids))
        rec.X = np.vstack([rec.X, rec_i.X[ids] * scale])
        rec.T[s], rec.obs[s] = T, (new, kp)
    counts["merged"] += len(extra)
    return extra
