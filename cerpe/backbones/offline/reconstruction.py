"""Metric reconstruction: points from a view's depth prior, the current view placed on them.

The view sharing most matches with the current one whose depth prior gives enough
keypoint depths (:data:`MIN_DEPTH_POINTS`) anchors the pass (the current view's own prior only when
no other view can); views are ranked by a cheap estimate first
(:meth:`.context.Pass.rank_by_shared`). The current view is placed on its points by P3P RANSAC.
Its candidates are up to ``motion_hypotheses`` rigid motions (each on the previous ones' outliers: the static
scene, a moving object, a facade matched one window off) plus the memo's previous
motion (constant velocity). The dense vote (:mod:`.vote`) decides between them, and
dense RGB-D alignment (:func:`cerpe.backbones.rgbd_align.align_rgbd`) refines the winner. This is how
RGB-D odometry uses depth: over short baselines it is far better conditioned than an
essential matrix, and it handles pure rotation. Other views are placed by absolute
pose on the points they share (:func:`place_pnp`).
"""
from __future__ import annotations

import time
from typing import Sequence

import numpy as np

from ...geometry import se3_inverse
from ..rgbd_align import align_rgbd, rgbd_pyramid
from . import framescale
from .context import P3P_SAMPLE, Pass, Recon
from .matching import keypoint_depths, pixels_to_rays, pose_to_T, reprojection_error
from .vote import moving_pixels, total_votes

MIN_DEPTH_POINTS = 50  # keypoint depths a view's prior needs to anchor the pass (else few-depth-points)
# P3P threshold of the current view on a prior (px): tighter than OfflineConfig.pnp_px so that a
# compromise between the scene and a moving object loses
DEPTH_PNP_PX = 2.0
MIN_PNP_INLIERS = 15  # 2D-3D inliers a view placed on the points needs (else the two-view fallback)


def bootstrap_depth(p: Pass) -> tuple[Recon | None, dict[int, str]]:
    """Points from a view with a usable metric depth prior and the current view placed on
    them; the memo of the current view is set (:meth:`Pass.remember`). Frame: the current
    camera; unit: metres. Returns the reconstruction (None: no prior worked) and a reason
    per view tried that did not work."""
    c = p.conf
    why: dict[int, str] = {}
    cands = [d for d in range(1, len(p.views)) if p.views[d].depth_m is not None and not p.low_tex[d]]
    cands = p.rank_by_shared(0, cands)  # the view sharing most matches first
    if p.views[0].depth_m is not None:
        cands.append(0)  # the current view's own points: only when no other view can anchor
    for d in cands:
        kp_uv = p.feats[d].keypoints
        z = keypoint_depths(kp_uv, p.views[d].depth_m, p.feats[d].image_hw)
        kp = np.flatnonzero(z > 0)
        if len(kp) < MIN_DEPTH_POINTS:
            why[d] = "few-depth-points"
            continue
        X_d = pixels_to_rays(kp_uv[kp], p.Ks[d]) * z[kp, None]
        ids = np.arange(len(kp))
        rec = Recon(X=X_d, T={d: np.eye(4)}, obs={d: (ids, kp)}, pair=(0, d), metric=True)
        if d == 0:
            return rec, why
        # constant velocity: the motion that placed d on its own prior, if d was placed so;
        # otherwise standing still (a sequence starts at rest: no velocity known yet)
        chain = p.chain(d)
        prior = chain[0][1] if chain else np.eye(4)
        if not place_pnp(p, 0, (d,), rec, min_inliers=c.min_inliers, hypotheses=c.motion_hypotheses,
                         ref_depth=d, px=DEPTH_PNP_PX, priors=[prior]):
            why[d] = "few-inliers"
            continue
        refine_dense(p, d, rec)
        if p.scale_ref is not None:
            # view 0's prior onto d's scale, measured on the refined pose: measured on the P3P pose,
            # the scale would absorb that pose's error along the optical axis, and the dense depth
            # term would then confirm it
            framescale.update_current(p, d, se3_inverse(rec.T[0]))
        tv = time.perf_counter()
        moving = moving_pixels(p, d, rec.T[0])
        p.timings["vote"] = p.timings.get("vote", 0.0) + time.perf_counter() - tv
        # re-anchor the frame on the current camera: rec.T[0] maps current-camera points into camera d
        T_c0_d = se3_inverse(rec.T.pop(0))
        p.remember(d, T_c0_d, moving)
        rec.X = rec.X @ T_c0_d[:3, :3].T + T_c0_d[:3, 3]
        rec.T = {0: np.eye(4), d: T_c0_d}
        add_current_prior_points(p, rec)
        return rec, why
    return None, why


def refine_dense(p: Pass, d: int, rec: Recon) -> None:
    """Dense RGB-D refinement of the current view's pose (``rec.T[0]``, frame: camera ``d``)
    on view ``d``'s depth prior; kept only when the aligner accepts it (counted either way)."""
    c = p.conf.dense
    if not c.refine or p.views[d].depth_m is None:
        return
    t0 = time.perf_counter()
    use_depth = c.use_depth and p.views[0].depth_m is not None
    pyramids = (pyramid(p, d, True, c.levels), pyramid(p, 0, use_depth, c.levels))
    res = align_rgbd(p.views[d].image, p.views[d].depth_m, p.views[0].image, p.views[0].depth_m,
                     p.Ks[d], p.Ks[0], se3_inverse(rec.T[0]), stride=c.stride, iterations=c.iterations,
                     levels=c.levels, use_depth=c.use_depth, pyramids=pyramids)
    if res.ok:
        rec.T[0] = se3_inverse(res.T_cur_ref)
        p.counts["dense-refined"] += 1
    else:
        p.counts[f"dense-refused:{res.reason}"] += 1
    p.timings["dense"] = p.timings.get("dense", 0.0) + time.perf_counter() - t0


def pyramid(p: Pass, k: int, with_depth: bool, levels: int) -> list:
    """View ``k``'s :func:`~cerpe.backbones.rgbd_align.rgbd_pyramid` (with its prior when ``with_depth``),
    kept by content (:meth:`Pass.derived`): this pass's current view is the next one's reference."""
    v = p.views[k]
    depth = v.depth_m if with_depth else None

    def make() -> list:
        return rgbd_pyramid(v.image, depth, p.Ks[k], levels, "reference depth" if k else "current depth")

    if not p.feats[k].fingerprint:
        return make()
    return p.derived(("rgbd-pyramid", p.feats[k].fingerprint, int(levels), *p.prior_key(k, with_depth)), make)


def add_current_prior_points(p: Pass, rec: Recon) -> None:
    """Back-project the current view's own prior at its keypoints that have no point yet, so
    views placed later (collaborators) find more 2D-3D correspondences."""
    if p.views[0].depth_m is None:
        return
    kp_uv = p.feats[0].keypoints
    z = keypoint_depths(kp_uv, p.views[0].depth_m, p.feats[0].image_hw)
    has = rec.kp_to_pt(0, p.feats[0].n) >= 0
    kp = np.flatnonzero((z > 0) & ~has)
    if len(kp) == 0:
        return
    ids0, kp0 = rec.obs[0]
    new_ids = np.arange(len(rec.X), len(rec.X) + len(kp))
    rec.X = np.vstack([rec.X, pixels_to_rays(kp_uv[kp], p.Ks[0]) * z[kp, None]])
    rec.obs[0] = (np.concatenate([ids0, new_ids]), np.concatenate([kp0, kp]))


def place_pnp(p: Pass, s: int, anchors: Sequence[int], rec: Recon, min_inliers: int | None = None,
              hypotheses: int = 1, ref_depth: int | None = None, px: float | None = None,
              priors: Sequence[np.ndarray] = ()) -> bool:
    """Absolute pose of view ``s`` from 2D-3D correspondences through its matches with the
    placed ``anchors``; writes ``rec.T[s]`` and ``rec.obs[s]`` on success (at least
    ``min_inliers`` inliers, default :data:`MIN_PNP_INLIERS`; RANSAC threshold ``px``, default
    ``pnp_px``).

    With ``hypotheses > 1`` RANSAC runs again on the previous runs' outliers. ``priors``
    (poses ``T_s_frame``) join as further hypotheses, refined on the correspondences
    they explain: an object holding most keypoints can take every RANSAC round, leaving
    the static scene out of the hypotheses. When ``s`` is view 0 and both it and
    ``ref_depth`` carry depth priors, the vote (:func:`.vote.choose_motion`) decides
    between hypotheses; otherwise the first (most inliers) wins."""
    import poselib

    cand_kp, cand_pt = [], []
    for a in anchors:
        if a == s or a not in rec.obs:
            continue
        m = p.m(a, s)
        pt = rec.kp_to_pt(a, p.feats[a].n)[m[:, 0]]
        cand_kp.append(m[pt >= 0, 1])
        cand_pt.append(pt[pt >= 0])
    if not cand_kp:
        return False
    kp = np.concatenate(cand_kp)
    pt = np.concatenate(cand_pt)
    _, first = np.unique(kp, return_index=True)  # one 3D point per keypoint of view s
    kp, pt = kp[first], pt[first]
    need = int(MIN_PNP_INLIERS if min_inliers is None else min_inliers)
    if len(kp) < need:
        return False
    rpx = float(p.conf.pnp_px if px is None else px)
    uv = p.feats[s].keypoints[kp].astype(np.float64)
    hyps: list[tuple[np.ndarray, np.ndarray]] = []
    left = np.ones(len(kp), bool)
    for _ in range(max(int(hypotheses), 1)):
        if left.sum() < need:
            break
        idx = np.flatnonzero(left)
        pose, info = poselib.estimate_absolute_pose(uv[idx], rec.X[pt[idx]], p.cams[s],
                                                    p.ransac((need, len(idx), P3P_SAMPLE), max_reproj_error=rpx), {})
        inl_sub = np.asarray(info["inliers"], bool)
        T_h = pose_to_T(pose.R, pose.t)
        if inl_sub.sum() < need or not np.all(np.isfinite(T_h)):
            break
        inl_h = np.zeros(len(kp), bool)
        inl_h[idx[inl_sub]] = True
        hyps.append((T_h, inl_h))
        left &= ~inl_h
    for T_prior in priors:
        h = prior_hypothesis(uv, rec.X[pt], p.cams[s], p.Ks[s], T_prior, rpx, need)
        if h is not None:
            hyps.append(h)
    if not hyps:
        return False
    T_s_f, inl = hyps[0]
    if len(hyps) > 1 and s == 0 and ref_depth is not None and p.views[0].depth_m is not None:
        # rec's frame is camera ref_depth here, so each T_h maps ref_depth's points into view 0
        tv = time.perf_counter()
        votes = total_votes(p, ref_depth, [T_h for T_h, _ in hyps])
        p.timings["vote"] = p.timings.get("vote", 0.0) + time.perf_counter() - tv
        T_s_f, inl = hyps[int(np.argmax(votes))]
    rec.T[s] = se3_inverse(T_s_f)
    rec.obs[s] = (pt[inl], kp[inl])
    return True


def prior_hypothesis(uv: np.ndarray, X: np.ndarray, cam: dict, K: np.ndarray, T_prior: np.ndarray,
                     px: float, need: int) -> tuple[np.ndarray, np.ndarray] | None:
    """``(T, inliers)`` of a pose hypothesis ``T_prior`` (points ``X`` into the camera)
    refined on the 2D-3D pairs it explains within ``2 px`` (it is only approximate),
    inliers then within ``px``; None when fewer than ``need``."""
    import poselib

    def inliers(T: np.ndarray, tol: float) -> np.ndarray:
        Xc = X @ T[:3, :3].T + T[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            err = reprojection_error(Xc, uv, K)
        return (Xc[:, 2] > 0) & (err < tol)

    T = np.asarray(T_prior, np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return None
    inl = inliers(T, 2 * px)
    if inl.sum() < need:
        return None
    pose = poselib.CameraPose()
    pose.R, pose.t = T[:3, :3], T[:3, 3]
    pose, _ = poselib.refine_absolute_pose(uv[inl], X[inl], pose, cam, {"loss_type": "CAUCHY", "loss_scale": px})
    T = pose_to_T(pose.R, pose.t)
    inl = inliers(T, px) if np.all(np.isfinite(T)) else np.zeros(len(uv), bool)
    return (T, inl) if inl.sum() >= need else None
