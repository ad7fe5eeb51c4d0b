"""The offline backbone: classical multi-view geometry behind :class:`cerpe.protocols.PoseBackbone`.

The stand-in for VGGT's joint pass over ``[current] + memory + collaborators``:
XFeat features (cached by content), mutual-nearest-neighbour matches (cached by
both images' content), then a metric reconstruction on the views' depth priors
(:mod:`.reconstruction`), and an image-only one (:mod:`.two_view`) where no prior
anchors or to add views the metric one left out. Per view: the pose in the current
camera's frame (``T_frame_cam[0] = I``), sparse depth of its inlier points and
confidence ``n_obs / (1 + reprojection error px)``.

Views that cannot be placed are ``valid=False`` with a reason (``few-matches``,
``few-inliers``, ``no-parallax``, ``few-3d-points``, ``few-depth-points``,
``no-reference``, ``low-texture``) and NaN poses. No exception leaves :meth:`infer`
for data reasons; a view without intrinsics, a malformed image or a memo that is
not this backbone's raise :class:`OfflineBackboneError`.

No state between calls: what a later pass needs about the current view goes out in
``BackboneOutput.memos[0]`` (see :mod:`.context`), so a pass depends on its views
(and their memos) alone.
"""
from __future__ import annotations

import time
from collections import Counter
from typing import Any, Sequence

import numpy as np

from ...geometry import se3_inverse
from ...config import merge_conf
from ...protocols import BackboneOutput, View
from ...scene import CameraIntrinsics
from ..rgbd_align import default_conf as dense_default_conf
from ..xfeat import XFeatEncoder, check_image, shared_encoder
from .context import OfflineBackboneError, Pass, Recon, check_memo
from .matching import PairMatcher, pinhole_camera, reprojection_error, splat_depth
from .reconstruction import bootstrap_depth, place_pnp
from .two_view import bootstrap, merge_image_only, two_view_with_scale


class OfflineGeometryBackbone:
    """XFeat + RANSAC + P3P on depth priors + dense refinement; see the module docstring.

    ``default_conf`` (pixels, degrees, counts, metres):
        xfeat: configuration of the shared :class:`XFeatEncoder`.
        min_cossim, ratio: matching (:func:`.matching.match_mnn`).
        match_cache_size: matched image pairs kept (LRU by content).
        min_matches: fewer matches -> ``few-matches``.
        epipolar_px, min_inliers, min_inlier_ratio: essential-matrix RANSAC threshold
            (Sampson px) and what a pair needs (-> ``few-inliers``).
        min_parallax_deg, parallax_quantile: that quantile of the reference pair's
            triangulation angles below the minimum -> ``no-parallax``.
        max_reproj_px, min_point_angle_deg: triangulated points kept.
        pnp_px, min_pnp_inliers: absolute-pose RANSAC threshold and the inliers a view
            needs (else the two-view fallback).
        min_scale_points: shared points the two-view fallback needs for its scale.
        min_texture_std: grey-level std below which an image is ``low-texture``.
        ransac_min_iterations, ransac_max_iterations: poselib's RANSAC bounds (its
            defaults cost a pair without overlap far more than the inlier ratios of
            overlapping frames need).
        depth_prior: anchor points on views' metric depth priors (False: image-only).
        depth_edge_tol, min_depth_points: keypoint depths kept (see
            :func:`.matching.keypoint_depths`) and how many a prior needs.
        depth_pnp_px: P3P threshold of the current view on a prior; tighter than
            ``pnp_px`` so that a compromise between the scene and a moving object loses.
        motion_hypotheses: rigid motions RANSAC looks for on a prior.
        vote_stride, vote_depth_tol, vote_grey_tol, vote_blur_sigma: the dense vote
            between them (:mod:`.vote`).
        motion_prior: the prior view's own motion (from its memo) joins as a hypothesis.
        vote_views, vote_chain_hops: older views that vote, reached through at most that
            many hops of the memos' motion chains.
        mask_moving: pixels a view's motion did not explain do not vote for the next one.
        dense_refine, dense: dense RGB-D refinement of the current pose on the prior view
            (``dense`` overrides :data:`cerpe.backbones.rgbd_align.default_conf`).
        dense_mask_moving: leave the prior view's moving pixels out of that refinement.
        merge_max_rot_px, merge_max_dir_deg, merge_max_ratio_spread, merge_min_baseline_m:
            agreement the image-only views need to join a metric pass
            (:func:`.two_view.merge_image_only`).

    ``counts`` accumulates events over passes (``dense-refined``, ``dense-refused:<why>``,
    ``merged``, ``merge-refused:<why>``); statistics only, they change no result.
    """

    default_conf: dict[str, Any] = {
        "xfeat": {},
        "min_cossim": 0.82,
        "ratio": 0.95,
        "match_cache_size": 256,
        "min_matches": 30,
        "epipolar_px": 1.0,
        "min_inliers": 25,
        "min_inlier_ratio": 0.2,
        "min_parallax_deg": 0.5,
        "parallax_quantile": 0.8,
        "max_reproj_px": 3.0,
        "min_point_angle_deg": 0.2,
        "pnp_px": 3.0,
        "min_pnp_inliers": 15,
        "min_scale_points": 8,
        "min_texture_std": 2.0,
        "ransac_min_iterations": 100,
        "ransac_max_iterations": 4000,
        "depth_prior": True,
        "depth_edge_tol": 0.2,
        "min_depth_points": 50,
        "depth_pnp_px": 2.0,
        "motion_hypotheses": 3,
        "vote_stride": 4,
        "vote_depth_tol": 0.05,
        "vote_grey_tol": 6.0,
        "vote_blur_sigma": 1.0,
        "motion_prior": True,
        "vote_views": 2,
        "vote_chain_hops": 12,
        "mask_moving": True,
        "dense_refine": True,
        "dense": {**dense_default_conf, "stride": 8, "iterations": 12},
        "dense_mask_moving": False,
        "merge_max_rot_px": 3.0,
        "merge_max_dir_deg": 10.0,
        "merge_max_ratio_spread": 1.25,
        "merge_min_baseline_m": 0.05,
    }

    def __init__(self, conf: dict[str, Any] | None = None, encoder: XFeatEncoder | None = None) -> None:
        self.conf = merge_conf(self.default_conf, conf, "offline backbone conf")
        self.encoder = encoder or shared_encoder(self.conf["xfeat"])
        self.matcher = PairMatcher(self.conf["min_cossim"], self.conf["ratio"], int(self.conf["match_cache_size"]))
        self.counts: Counter[str] = Counter()

    def clear_caches(self) -> None:
        """Forget cached matches (a cold start; features live in the encoder's cache)."""
        self.matcher.clear()

    def infer(self, views: Sequence[View]) -> BackboneOutput:
        """One joint pass over ``[current] + keyframes + previous frame + collaborators``."""
        S = len(views)
        if S == 0:
            raise OfflineBackboneError("offline backbone: no views given")
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        intr: list[CameraIntrinsics] = []
        for s, v in enumerate(views):
            if v.intrinsics is None:
                raise OfflineBackboneError(
                    f"offline backbone: view {s} (key {v.key!r}) has no intrinsics; this backbone needs them")
            check_image(v.image, f"view {s} (key {v.key!r})", int(self.encoder.conf["min_size"]))
            intr.append(v.intrinsics)
        feats = [self.encoder.encode(v) for v in views]
        timings["encode"] = time.perf_counter() - t0
        memos = [None] + [check_memo(v, s, f) for s, (v, f) in enumerate(zip(views, feats)) if s > 0]
        p = Pass(views=views, feats=feats, Ks=[i.K for i in intr], cams=[pinhole_camera(i) for i in intr],
                 low_tex=[f.grey_std < self.conf["min_texture_std"] for f in feats], conf=self.conf,
                 matcher=self.matcher, memos=memos, timings=timings)
        rec, reasons = self._solve(p)
        self.counts.update(p.counts)
        T = np.full((S, 4, 4), np.nan)
        valid = np.zeros(S, bool)
        valid[0] = True
        if rec is None:
            T[0] = np.eye(4)
        else:
            for s, Ts in rec.T.items():
                T[s] = Ts
                valid[s] = True
        depth, conf = _depth_maps(p, rec, valid)
        timings["total"] = time.perf_counter() - t0
        reference = rec.pair[1] if rec is not None and rec.metric and rec.pair[1] != 0 else None
        return BackboneOutput(T_frame_cam=T, valid=valid, depth=depth, depth_conf=conf,
                              intrinsics=list(intr), reasons=reasons, timings_s=timings,
                              metric_unit=rec is not None and rec.metric, reference=reference,
                              memos=[p.memo_out] + [None] * (S - 1))

    def _solve(self, p: Pass) -> tuple[Recon | None, list[str]]:
        """The reconstruction of this pass (None: nothing placed besides view 0) and reasons.

        The metric (depth-anchored) reconstruction comes first. When it leaves out a view
        with enough matches to the current one, the image-only one is built too and the
        views only it placed join (:func:`.two_view.merge_image_only`): a prior never costs
        a direct estimate the images support, and an image-only pass (whose two-view poses
        over forward motion are far less accurate) never replaces a metric one."""
        S = len(p.views)
        if S == 1:
            return None, [""]
        if p.low_tex[0] or p.feats[0].n < self.conf["min_matches"]:
            return None, [""] + ["low-texture" if p.low_tex[0] else "few-matches"] * (S - 1)
        if not self.conf["depth_prior"]:
            return _solve_once(p, metric=False)
        rec, reasons = _solve_once(p, metric=True)
        if rec is not None and not _retry_image_only(p, rec):
            return rec, reasons
        rec_i, reasons_i = _solve_once(p, metric=False)
        if rec is None:
            # nothing placed either way: the image-only attempt's reasons say more (parallax, texture)
            return rec_i, reasons_i
        if rec_i is not None:
            for s in merge_image_only(rec, rec_i, float(p.Ks[0][0, 0]), self.conf, p.counts):
                reasons[s] = ""
        return rec, reasons


def _retry_image_only(p: Pass, rec: Recon) -> bool:
    """Whether the image-only solve could place a view ``rec`` left out: one with at least
    ``min_pnp_inliers`` matches with the current view. A collaborator image without
    overlap has fewer, and re-solving for it would only double the pass's cost."""
    need = int(p.conf["min_pnp_inliers"])
    return any(s not in rec.T and not p.low_tex[s] and len(p.m(0, s)) >= need for s in range(1, len(p.views)))


def _solve_once(p: Pass, metric: bool) -> tuple[Recon | None, list[str]]:
    """One reconstruction (metric: on a depth prior; else image-only) and every view placed on it."""
    S = len(p.views)
    reasons = [""] + ["no-reference"] * (S - 1)
    tg = time.perf_counter()
    rec, why = bootstrap_depth(p) if metric else bootstrap(p, 0, range(1, S))
    p.timings["two_view"] = p.timings.get("two_view", 0.0) + time.perf_counter() - tg
    if rec is None:
        return None, [""] + [why.get(s) or "no-reference" for s in range(1, S)]
    tp = time.perf_counter()
    anchors = (0,) + tuple(a for a in rec.pair if a != 0)[:1]
    for s in range(1, S):
        if s in rec.T:
            continue
        if p.low_tex[s]:
            reasons[s] = "low-texture"
        elif not place_pnp(p, s, anchors, rec):
            reasons[s] = two_view_with_scale(p, s, rec)
            reasons[s] = (why.get(s) or reasons[s]) if reasons[s] else ""
    for s in rec.T:
        reasons[s] = ""
    p.timings["pnp"] = p.timings.get("pnp", 0.0) + time.perf_counter() - tp
    return rec, reasons


def _depth_maps(p: Pass, rec: Recon | None, valid: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per view sparse depth of its observed points and confidence ``n_obs / (1 + err px)``."""
    hw = [f.image_hw for f in p.feats]
    depth = [np.zeros(h, np.float32) for h in hw]
    conf = [np.zeros(h, np.float32) for h in hw]
    if rec is None:
        return depth, conf
    n_obs = np.zeros(len(rec.X))
    for ids, _ in rec.obs.values():
        np.add.at(n_obs, ids, 1)
    for s, (ids, kp) in rec.obs.items():
        if not valid[s]:
            continue
        Tsf = se3_inverse(rec.T[s])
        Xs = rec.X[ids] @ Tsf[:3, :3].T + Tsf[:3, 3]
        uv = p.feats[s].keypoints[kp]
        err = reprojection_error(Xs, uv, p.Ks[s])
        depth[s], conf[s] = splat_depth(uv, Xs[:, 2], n_obs[ids] / (1.0 + np.minimum(err, 1e3)), hw[s])
    return depth, conf
