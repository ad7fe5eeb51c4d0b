"""Multi-view geometry backbone that runs offline: XFeat matching + RANSAC + triangulation + PnP.

Implements :class:`cerpe.protocols.PoseBackbone` without a learned multi-view
model. The stand-in for VGGT's joint pass over ``[current] + memory +
collaborators`` is classical structure from motion:

1. Features: XFeat keypoints per view (:mod:`cerpe.backbones.xfeat`, cached per key).
2. Matching: mutual nearest neighbours of the 64-d descriptors with a minimum
   cosine similarity and Lowe's ratio test. Matches between two views seen
   before (e.g. two keyframes) come from an LRU cache keyed by both view keys.
3. Points anchored on metric depth (``depth_prior``, the default): a view that
   carries a depth prior (:attr:`View.depth_m`; the algorithm attaches each
   keyframe's metric depth reference, the previous frame's and the current
   frame's) gives 3D points by back-projecting its keypoints with that depth
   (keypoints on a depth edge are dropped). The view sharing most matches with
   the current one is tried first; the current view's own prior only when no
   other view anchors. The current view is placed on them by absolute pose (P3P
   RANSAC, up to three motion hypotheses and the previous motion decided by a
   dense vote of depth and grey-level consistency, cast by the prior's view and
   by up to two older keyframes reached through the stored motions; pixels of the
   prior's view that its own motion did not explain, a moving object, do not
   vote), its pose refined by dense
   photometric + depth alignment (:mod:`cerpe.backbones.rgbd_align`); then the
   current view's own prior adds its points too. The unit of the pass is then the metre (``BackboneOutput.metric_unit``),
   so the algorithm has no scale to recover. This is how RGB-D odometry
   uses a depth sensor; it replaces the two-view essential matrix, whose
   translation direction is off by degrees over the short baselines between
   consecutive frames, and it is not fooled by objects that move (they are
   P3P outliers) or by pure rotation. VGGT never reads the prior.
4. Otherwise (no prior, or too few points on it) a reference pair: the current
   view (index 0, the pass's frame: ``T_frame_cam[0] = I``) and the first
   candidate (newest keyframe, then older keyframes, then collaborators) whose
   essential matrix (poselib 5-point RANSAC, known intrinsics) has enough
   inliers and enough parallax. Its baseline defines the unit of the pass
   (``||t|| = 1``). Its inliers are triangulated (linear, in the current camera
   frame); points behind a camera, with large reprojection error or a small
   triangulation angle are dropped.
5. Every other view: absolute pose (poselib P3P RANSAC + refinement) from 2D-3D
   correspondences obtained through its matches with the current view and with
   the reference view; if too few, a two-view fallback (essential matrix with
   the current view; translation scale from the depths of the shared
   triangulated points). When the depth-anchored pass leaves out a view that the
   image-only one (step 4) places, that view joins the metric pass at the scale
   of the views both placed, if the two agree on them (``_merge_image_only``).
6. Per-view sparse depth: the inlier points' camera-frame depths splatted at
   their pixels (0 elsewhere), confidence ``n_obs / (1 + reprojection error px)``.

Views that cannot be placed are ``valid=False`` with a reason (``few-matches``,
``few-inliers``, ``no-parallax``, ``few-3d-points``, ``no-reference``,
``low-texture``); their pose rows are NaN. No exception leaves :meth:`infer`
for data reasons; a view without intrinsics or with a malformed image raises
:class:`OfflineBackboneError` (a configuration/programming error).
"""
from __future__ import annotations

import logging
import time
from collections import Counter, OrderedDict
from dataclasses import dataclass, field
from typing import Any, Hashable, Sequence

import numpy as np

from ..protocols import BackboneError, BackboneOutput, View
from ..scene import CameraIntrinsics
from .rgbd_align import align_rgbd, grey_image
from .xfeat import XFeatEncoder, XFeatFeatures, check_image, shared_encoder

logger = logging.getLogger(__name__)


class OfflineBackboneError(BackboneError):
    """A view the offline backbone cannot take at all (no intrinsics, malformed image)."""


# ---------------------------------------------------------------------------- pure helpers
def match_mnn(desc0: np.ndarray, desc1: np.ndarray, min_cossim: float = 0.82,
              ratio: float = 0.95) -> np.ndarray:
    """Mutual nearest-neighbour matches of L2-normalised descriptors.

    Args:
        desc0: ``[N0,D]``; desc1: ``[N1,D]`` (unit rows).
        min_cossim: a match needs cosine similarity above this.
        ratio: Lowe's ratio on distances (best / second best) must be below it
            in both directions (1 disables it).

    Returns:
        ``[M,2] int64`` index pairs ``(i0, i1)``.
    """
    if len(desc0) == 0 or len(desc1) == 0:
        return np.zeros((0, 2), np.int64)
    import torch

    with torch.inference_mode():
        sim = torch.from_numpy(np.ascontiguousarray(desc0, np.float32)) @ torch.from_numpy(
            np.ascontiguousarray(desc1, np.float32)).T
        k0 = min(2, sim.shape[1])
        k1 = min(2, sim.shape[0])
        top01, idx01 = torch.topk(sim, k0, dim=1)
        # top-k along rows of a contiguous transpose: torch's column-wise topk is about 2x slower
        top10, idx10 = torch.topk(sim.T.contiguous(), k1, dim=1)
        top10, idx10 = top10.T, idx10.T
        nn01 = idx01[:, 0].numpy()
        nn10 = idx10[0, :].numpy()
        best = top01[:, 0].numpy().astype(np.float64)
        i0 = np.arange(len(desc0))
        keep = (nn10[nn01] == i0) & (best > min_cossim)
        if ratio < 1.0 and k0 == 2 and k1 == 2:
            # distances of unit vectors: d^2 = 2 - 2 cos
            second01 = top01[:, 1].numpy().astype(np.float64)
            second10 = top10[1, :].numpy().astype(np.float64)[nn01]
            d_best = np.sqrt(np.maximum(2 - 2 * best, 0))
            keep &= d_best < ratio * np.sqrt(np.maximum(2 - 2 * second01, 0))
            keep &= d_best < ratio * np.sqrt(np.maximum(2 - 2 * second10, 0))
    return np.stack([i0[keep], nn01[keep]], axis=1).astype(np.int64)


def pixels_to_rays(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """``[N,2]`` pixels -> ``[N,3]`` normalised camera rays ``(x, y, 1)``."""
    return np.column_stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))])


def triangulate(rays0: np.ndarray, rays1: np.ndarray, T_1_0: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation of ray pairs; points in camera-0 coordinates.

    Args:
        rays0, rays1: ``[N,3]`` normalised rays ``(x, y, 1)`` in cameras 0 and 1.
        T_1_0: ``[4,4]`` maps camera-0 points into camera 1.

    Returns:
        ``[N,3]`` points (may be NaN/inf for degenerate rays; callers filter).
    """
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
    """Pixel distance between projected camera-frame points ``[N,3]`` and ``uv [N,2]``."""
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


def _pose_to_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, float)
    T[:3, 3] = np.asarray(t, float).ravel()
    return T


def _inv(T: np.ndarray) -> np.ndarray:
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


def _camera(intr: CameraIntrinsics) -> dict[str, Any]:
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


def _map_index(x: np.ndarray, n_map: int, n_img: int) -> np.ndarray:
    """Index along one axis of a ``n_map``-pixel map under image coordinate ``x`` of an
    ``n_img``-pixel image (nearest neighbour on pixel centres, clipped to the map)."""
    return np.clip(np.floor((x + 0.5) * n_map / n_img).astype(np.int64), 0, n_map - 1)


def keypoint_depths(uv: np.ndarray, depth_m: np.ndarray, image_hw: tuple[int, int],
                    edge_tol: float = 0.2, min_valid: int = 5) -> np.ndarray:
    """Metric depth at keypoints ``uv [N,2]`` (image pixels) from a depth map of any size.

    The map is sampled by nearest neighbour on pixel centres. Each keypoint takes
    the median of the known pixels (> 0, finite) of its 3x3 neighbourhood, which
    also damps per-pixel sensor noise. It gets 0 (unknown) when fewer than
    ``min_valid`` of the 9 are known or when they spread by more than
    ``edge_tol`` relative to that median: keypoints sit on corners and edges,
    where one pixel off is the background.

    Returns:
        ``[N] float64`` depths in metres, 0 where unknown.
    """
    D = np.asarray(depth_m, np.float64)
    if D.ndim != 2 or D.size == 0 or len(uv) == 0:
        return np.zeros(len(uv))
    H, W = image_hw
    hd, wd = D.shape
    u = _map_index(uv[:, 0], wd, W) + 1  # + 1: the padded border
    v = _map_index(uv[:, 1], hd, H) + 1
    P = np.pad(np.where(np.isfinite(D) & (D > 0), D, np.nan), 1, constant_values=np.nan)
    win = np.stack([P[v + dv, u + du] for dv in (-1, 0, 1) for du in (-1, 0, 1)], axis=1)  # [N,9]
    n = np.sum(np.isfinite(win), axis=1)
    out = np.zeros(len(uv))
    ok = n >= min_valid
    if ok.any():
        w = win[ok]
        z = np.nanmedian(w, axis=1)
        spread = (np.nanmax(w, axis=1) - np.nanmin(w, axis=1)) / z
        out[np.flatnonzero(ok)] = np.where(spread <= edge_tol, z, 0.0)
    return out


# ---------------------------------------------------------------------------- the backbone
@dataclass
class _Recon:
    """Points and placed views of one reconstruction (frame: its anchor view's camera).

    Attributes:
        X: ``[P,3]`` points in the frame.
        T: view index -> ``T_frame_view [4,4]`` (metric up to the pass's unit).
        obs: view index -> ``(point ids [M], keypoint ids [M])`` of that view.
        pair: the two views whose essential matrix made the points (anchor first).
    """

    X: np.ndarray
    T: dict[int, np.ndarray] = field(default_factory=dict)
    obs: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    pair: tuple[int, int] = (0, 0)
    metric: bool = False  # the unit is the metre: the points came from a depth prior

    def kp_to_pt(self, s: int, n_kp: int) -> np.ndarray:
        """``[n_kp]`` point id of each keypoint of view ``s`` (-1: none)."""
        a = np.full(n_kp, -1, np.int64)
        if s in self.obs:
            ids, kp = self.obs[s]
            a[kp] = ids
        return a


@dataclass
class _Pass:
    """Per-call inputs shared by the helpers."""

    views: Sequence[View]
    feats: list[XFeatFeatures]
    Ks: list[np.ndarray]
    cams: list[dict]
    low_tex: list[bool]
    timings: dict[str, float] = field(default_factory=dict)
    # (a, b) -> essential-matrix result of views a and b (the depth-anchored and the
    # image-only solves of one pass ask for the same pairs)
    relative: dict[tuple[int, int], tuple[np.ndarray | None, np.ndarray, str]] = field(default_factory=dict)


class OfflineGeometryBackbone:
    """Classical multi-view geometry behind the :class:`~cerpe.protocols.PoseBackbone` protocol.

    ``default_conf`` (thresholds in pixels / degrees / counts):
        xfeat: configuration of the shared :class:`XFeatEncoder`.
        min_cossim, ratio: matching (see :func:`match_mnn`).
        match_cache_size: matched view pairs kept (LRU).
        min_matches: fewer matches than this -> ``few-matches``.
        epipolar_px: RANSAC threshold of the essential matrix (Sampson, px).
        min_inliers: fewer essential-matrix inliers -> ``few-inliers``.
        min_inlier_ratio: inliers / matches below this -> ``few-inliers``.
        min_parallax_deg, parallax_quantile: the ``parallax_quantile`` quantile of the
            triangulation angles of the reference pair's inliers below ``min_parallax_deg``
            this -> ``no-parallax`` (pure rotation, tiny baseline).
        max_reproj_px: triangulated points reprojecting worse are dropped.
        min_point_angle_deg: points with a smaller triangulation angle are dropped.
        pnp_px: RANSAC threshold of the absolute pose (px).
        min_pnp_inliers: fewer 2D-3D inliers -> two-view fallback.
        min_scale_points: shared points the two-view fallback needs for its scale.
        min_texture_std: grey-level standard deviation below which an image is
            ``low-texture`` (blank, black).
        ransac_min_iterations: poselib's lower bound on RANSAC iterations (its default,
            1000, is far more than the adaptive stopping rule needs at the inlier
            ratios of consecutive frames).
        ransac_max_iterations: poselib's upper bound (its default, 100000, is what a pair
            that does not overlap costs: a few hundred milliseconds for nothing; 4000 still
            finds a 5-point model at a 25 % inlier ratio with probability 0.98, at 30 %
            with 0.9999).
        depth_prior: anchor the points on a view's metric depth prior when one is
            given (False: image-only, the essential-matrix path for every pass).
        depth_edge_tol: keypoints whose 3x3 prior depth spreads by more than this
            fraction of its median are not used (see :func:`keypoint_depths`).
        min_depth_points: a prior needs this many keypoints with depth.
        depth_pnp_px: RANSAC threshold (px) of the current view on a depth prior; tighter
            than ``pnp_px`` because with metric points a looser one lets a compromise
            between the static scene and a moving object win.
        motion_hypotheses: rigid motions RANSAC looks for when placing the current view
            on a depth prior (each on the previous ones' outliers, each with at least
            ``min_inliers``): the static scene, moving objects, a facade matched one
            window off.
        vote_stride, vote_depth_tol, vote_grey_tol, vote_blur_sigma: pixel stride, relative
            depth tolerance, grey-level tolerance (0-255) and blur of the dense vote that
            picks between them (see ``_motion_votes``).
        motion_prior: offer the motion that placed the depth-prior view on its own prior
            (constant velocity; no motion when there is none yet) as one more hypothesis to
            the vote (see ``_place_pnp``).
        vote_views, vote_chain_hops: older views of the pass (keyframes) that vote too, at
            most this many, reached by following each view's stored motion to its anchor
            for at most this many steps (see ``_chained_views``).
        mask_moving: pixels of a view that its chosen motion did not explain (depth or grey
            level off: a moving object) do not vote when that view is the next pass's prior
            (see ``_note_moving``).
        dense_refine, dense: refine the current view's pose on the depth-prior view by
            dense photometric + depth alignment (:func:`cerpe.backbones.rgbd_align.align_rgbd`,
            ``dense`` overrides its ``default_conf``). Keypoints place the current view to
            about 0.5 px; consecutive frames 4 cm apart then show ego-motion errors of
            2-3 mm a step (6 % of the path), every pixel brings it to about 0.2 mm. Up to
            12 Gauss-Newton steps per level (the aligner's default is 6): when the keypoints
            sit on a far wall and a moving object, the keypoint pose can be off by a
            sideways shift plus a turn (4 cm and 0.5 degrees on indoor e00 r0), which the
            floor's texture corrects only over more steps. A refinement the aligner refuses
            leaves the P3P pose as it is (counted in ``n_dense_refused``).
        dense_mask_moving: leave the prior view's pixels found moving (``mask_moving``)
            out of the dense refinement (``align_rgbd``'s ``mask_ref``). Off by default:
            from a start 1-2 cm off, a textured cart close to the camera holds the dense
            pose 1-1.5 cm off unless masked, but the P3P start here is within a few
            millimetres, and on the synthetic suite the mask changed ego RPE by
            +0.11 (indoor r0) and +0.02 (CAD r1) percentage points, nothing better.
        merge_max_rot_px, merge_max_dir_deg, merge_max_ratio_spread, merge_min_baseline_m:
            when the image-only reconstruction places views the depth one left out, they
            join it only if the two agree this well on the views both placed (see
            ``_merge_image_only``; refusals counted in ``n_merge_refused``).
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
        # a high quantile, not the median: forward motion has near-zero parallax at the
        # focus of expansion but enough at the image sides; pure rotation has none anywhere
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
        "dense": {"stride": 8, "iterations": 12},
        "dense_mask_moving": False,
        "merge_max_rot_px": 3.0,
        "merge_max_dir_deg": 10.0,
        "merge_max_ratio_spread": 1.25,
        "merge_min_baseline_m": 0.05,
    }

    def __init__(self, conf: dict[str, Any] | None = None, encoder: XFeatEncoder | None = None) -> None:
        self.conf = {**self.default_conf, **(conf or {})}
        self.encoder = encoder or shared_encoder(self.conf["xfeat"])
        self._matches: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self.n_match_computed = 0
        self.n_match_cached = 0
        self.n_dense_refined = 0
        self.n_dense_refused: Counter[str] = Counter()
        self.n_merged = 0  # views the image-only reconstruction added to a metric one
        self.n_merge_refused: Counter[str] = Counter()
        # key of a view placed on a depth prior -> (key of that prior's view, T_view_prior):
        # the previous motion, offered as a hypothesis when the view is itself the prior
        self._motions: OrderedDict[Hashable, tuple[Hashable, np.ndarray]] = OrderedDict()
        # key of a view placed on a depth prior -> its vote-grid pixels that the chosen motion
        # did not explain (``_note_moving``); they do not vote when the view is itself the prior
        self._moving: OrderedDict[Hashable, np.ndarray] = OrderedDict()

    def clear_caches(self) -> None:
        """Forget cached matches and motions (a cold start; features live in the encoder's cache)."""
        self._matches.clear()
        self._motions.clear()
        self._moving.clear()

    # ------------------------------------------------------------------ matching with cache
    def _match(self, ka: Hashable, fa: XFeatFeatures, kb: Hashable, fb: XFeatFeatures) -> np.ndarray:
        # the pixel fingerprint keeps a collaborator's JPEG copy apart from the original with the same key
        ka, kb = (ka, fa.fingerprint), (kb, fb.fingerprint)
        key = (ka, kb)
        m = self._matches.get(key)
        if m is not None:
            self._matches.move_to_end(key)
            self.n_match_cached += 1
            return m
        rkey = (kb, ka)
        if rkey in self._matches:
            self.n_match_cached += 1
            return self._matches[rkey][:, ::-1]
        m = match_mnn(fa.descriptors, fb.descriptors, self.conf["min_cossim"], self.conf["ratio"])
        self.n_match_computed += 1
        self._matches[key] = m
        while len(self._matches) > int(self.conf["match_cache_size"]):
            self._matches.popitem(last=False)
        return m

    def _m(self, p: _Pass, a: int, b: int) -> np.ndarray:
        """``[M,2]`` keypoint index pairs between views ``a`` and ``b`` (empty for low texture)."""
        if p.low_tex[a] or p.low_tex[b]:
            return np.zeros((0, 2), np.int64)
        return self._match(p.views[a].key, p.feats[a], p.views[b].key, p.feats[b])

    def _ransac(self, **extra: float) -> dict[str, float]:
        return {"min_iterations": int(self.conf["ransac_min_iterations"]),
                "max_iterations": int(self.conf["ransac_max_iterations"]), **extra}

    # ------------------------------------------------------------------ two-view geometry
    def _relative_pose(self, uv0: np.ndarray, uv1: np.ndarray, cam0: dict, cam1: dict
                       ) -> tuple[np.ndarray | None, np.ndarray, str]:
        """Essential-matrix RANSAC: ``T_1_0`` with unit translation, inlier mask, reason."""
        import poselib

        c = self.conf
        if len(uv0) < c["min_matches"]:
            return None, np.zeros(len(uv0), bool), "few-matches"
        pose, info = poselib.estimate_relative_pose(
            uv0.astype(np.float64), uv1.astype(np.float64), cam0, cam1,
            self._ransac(max_epipolar_error=float(c["epipolar_px"])), {})
        inl = np.asarray(info["inliers"], bool)
        if inl.sum() < c["min_inliers"] or inl.mean() < c["min_inlier_ratio"]:
            return None, inl, "few-inliers"
        T = _pose_to_T(pose.R, pose.t)
        if not np.all(np.isfinite(T)) or np.linalg.norm(T[:3, 3]) < 1e-9:
            return None, inl, "few-inliers"
        T[:3, 3] /= np.linalg.norm(T[:3, 3])
        return T, inl, ""

    def _pair_pose(self, p: _Pass, a: int, b: int) -> tuple[np.ndarray | None, np.ndarray, str]:
        """:meth:`_relative_pose` of views ``a`` and ``b`` over their matches, once per pass."""
        if (a, b) not in p.relative:
            m = self._m(p, a, b)
            p.relative[(a, b)] = self._relative_pose(p.feats[a].keypoints[m[:, 0]], p.feats[b].keypoints[m[:, 1]],
                                                     p.cams[a], p.cams[b])
        return p.relative[(a, b)]

    def _triangulate_pair(self, uv0: np.ndarray, uv1: np.ndarray, K0: np.ndarray, K1: np.ndarray,
                          T_1_0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Points in camera 0, a keep mask, mean reprojection error (px) and triangulation angle (deg)."""
        X = triangulate(pixels_to_rays(uv0, K0), pixels_to_rays(uv1, K1), T_1_0)
        X1 = X @ T_1_0[:3, :3].T + T_1_0[:3, 3]
        e0 = reprojection_error(X, uv0, K0)
        e1 = reprojection_error(X1, uv1, K1)
        ang = triangulation_angle_deg(X, np.zeros(3), _inv(T_1_0)[:3, 3])
        keep = (np.all(np.isfinite(X), axis=1) & (X[:, 2] > 0) & (X1[:, 2] > 0)
                & (e0 < self.conf["max_reproj_px"]) & (e1 < self.conf["max_reproj_px"]))
        return X, keep & (ang >= self.conf["min_point_angle_deg"]), 0.5 * (e0 + e1), ang

    def _bootstrap(self, p: _Pass, anchor: int, cands: Sequence[int]) -> tuple[_Recon | None, dict[int, str]]:
        """Points from ``anchor`` and the first candidate with a good essential matrix and
        parallax. Returns the reconstruction (frame: ``anchor``'s camera) and a reason per
        candidate tried that did not work."""
        c = self.conf
        why: dict[int, str] = {}
        for s in cands:
            if p.low_tex[s]:
                why[s] = "low-texture"
                continue
            m = self._m(p, anchor, s)
            uva, uvs = p.feats[anchor].keypoints[m[:, 0]], p.feats[s].keypoints[m[:, 1]]
            T_s_a, inl, reason = self._pair_pose(p, anchor, s)
            if T_s_a is None:
                why[s] = reason
                continue
            X, keep, _, ang = self._triangulate_pair(uva[inl], uvs[inl], p.Ks[anchor], p.Ks[s], T_s_a)
            parallax = float(np.quantile(ang, c["parallax_quantile"]))
            if parallax < c["min_parallax_deg"]:
                why[s] = "no-parallax"
                continue
            if keep.sum() < c["min_inliers"]:
                why[s] = "few-3d-points"
                continue
            mi = m[inl][keep]
            ids = np.arange(len(mi))
            return _Recon(X=X[keep], T={anchor: np.eye(4), s: _inv(T_s_a)},
                          obs={anchor: (ids, mi[:, 0]), s: (ids, mi[:, 1])}, pair=(anchor, s)), why
        return None, why

    def _bootstrap_depth(self, p: _Pass) -> tuple[_Recon | None, dict[int, str]]:
        """Points from a view with a usable metric depth prior, current view placed on them by
        P3P (module docstring, step 3). Frame: the current camera; unit: metres."""
        c = self.conf
        why: dict[int, str] = {}
        cands = [d for d in range(1, len(p.views)) if p.views[d].depth_m is not None and not p.low_tex[d]]
        cands.sort(key=lambda d: -len(self._m(p, 0, d)))  # the view sharing most matches first
        if p.views[0].depth_m is not None:
            cands.append(0)  # the current view's own points: only when no other view can anchor
        for d in cands:
            kp_uv = p.feats[d].keypoints
            z = keypoint_depths(kp_uv, p.views[d].depth_m, p.feats[d].image_hw, float(c["depth_edge_tol"]))
            kp = np.flatnonzero(z > 0)
            if len(kp) < c["min_depth_points"]:
                why[d] = "few-depth-points"
                continue
            X_d = pixels_to_rays(kp_uv[kp], p.Ks[d]) * z[kp, None]
            ids = np.arange(len(kp))
            rec = _Recon(X=X_d, T={d: np.eye(4)}, obs={d: (ids, kp)}, pair=(0, d), metric=True)
            if d == 0:
                return rec, why
            # constant velocity: the motion that placed d on its own prior, if d was placed so;
            # otherwise standing still (a sequence starts at rest: no velocity known yet)
            prior = self._motions.get(p.views[d].key) if c["motion_prior"] else None
            if not self._place_pnp(p, 0, (d,), rec, min_inliers=int(c["min_inliers"]),
                                   hypotheses=int(c["motion_hypotheses"]), ref_depth=d, px=float(c["depth_pnp_px"]),
                                   priors=[prior[1] if prior is not None else np.eye(4)]):
                why[d] = "few-inliers"
                continue
            self._refine_dense(p, d, rec)
            self._note_moving(p, d, rec.T[0])
            self._motions[p.views[0].key] = (p.views[d].key, _inv(rec.T[0]))
            while len(self._motions) > int(c["match_cache_size"]):
                self._motions.popitem(last=False)
            # re-anchor the frame on the current camera: rec.T[0] maps current-camera points into camera d
            T_c0_d = _inv(rec.T.pop(0))
            rec.X = rec.X @ T_c0_d[:3, :3].T + T_c0_d[:3, 3]
            rec.T = {0: np.eye(4), d: T_c0_d}
            self._add_current_prior_points(p, rec)
            return rec, why
        return None, why

    def _refine_dense(self, p: _Pass, d: int, rec: _Recon) -> None:
        """Dense RGB-D refinement of the current view's pose (``rec.T[0]``, frame: camera ``d``)
        on view ``d``'s depth prior; kept only when the aligner accepts it."""
        if not self.conf["dense_refine"] or p.views[d].depth_m is None:
            return
        t0 = time.perf_counter()
        moving = self._moving.get(p.views[d].key) if self.conf["dense_mask_moving"] else None
        mask = None if moving is None else self._grid_mask_image(moving, p.feats[d].image_hw)
        res = align_rgbd(p.views[d].image, p.views[d].depth_m, p.views[0].image, p.views[0].depth_m,
                         p.Ks[d], p.Ks[0], _inv(rec.T[0]), self.conf["dense"], mask_ref=mask)
        if res.ok:
            rec.T[0] = _inv(res.T_cur_ref)
            self.n_dense_refined += 1
        else:
            self.n_dense_refused[res.reason] += 1
        p.timings["dense"] = p.timings.get("dense", 0.0) + time.perf_counter() - t0

    def _grid_mask_image(self, grid: np.ndarray, image_hw: tuple[int, int]) -> np.ndarray:
        """``[H,W]`` bool image of a ``[n_grid]`` mask on the ``vote_stride`` grid of
        :meth:`_consistency`, each grid pixel covering its cell. Lone grid pixels (a grey
        level off at a texture edge, sensor noise) are dropped by an opening; what is left,
        an object, grows by one cell (its outline falls between grid pixels)."""
        import cv2

        H, W = image_hw
        st = max(int(self.conf["vote_stride"]), 1)
        gh, gw = len(range(st // 2, H, st)), len(range(st // 2, W, st))
        box = np.ones((3, 3), np.uint8)
        cells = cv2.morphologyEx(np.asarray(grid, np.uint8).reshape(gh, gw), cv2.MORPH_OPEN, box)
        cells = cv2.dilate(cells, box)
        rows, cols = np.minimum(np.arange(H) // st, gh - 1), np.minimum(np.arange(W) // st, gw - 1)
        return cells[rows[:, None], cols[None, :]].astype(bool)

    def _add_current_prior_points(self, p: _Pass, rec: _Recon) -> None:
        """Back-project the current view's own prior at its keypoints that have no point yet, so
        views placed later (collaborators) find more 2D-3D correspondences."""
        if p.views[0].depth_m is None:
            return
        kp_uv = p.feats[0].keypoints
        z = keypoint_depths(kp_uv, p.views[0].depth_m, p.feats[0].image_hw, float(self.conf["depth_edge_tol"]))
        has = rec.kp_to_pt(0, p.feats[0].n) >= 0
        kp = np.flatnonzero((z > 0) & ~has)
        if len(kp) == 0:
            return
        ids0, kp0 = rec.obs[0]
        new_ids = np.arange(len(rec.X), len(rec.X) + len(kp))
        rec.X = np.vstack([rec.X, pixels_to_rays(kp_uv[kp], p.Ks[0]) * z[kp, None]])
        rec.obs[0] = (np.concatenate([ids0, new_ids]), np.concatenate([kp0, kp]))

    def _motion_votes(self, p: _Pass, d: int, T_0_d: Sequence[np.ndarray]) -> np.ndarray:
        """Dense votes of view ``d``'s prior depth pixels for the motions ``T_0_d[h]``
        (camera-``d`` points into the current camera).

        Each sampled pixel of ``d`` (every ``vote_stride``-th) is back-projected with its
        prior depth, moved by every hypothesis into the current view and, if it lands in
        the image under all of them, counts for each hypothesis under which it is
        *consistent* (:meth:`_consistency`). Both tests matter: depth alone cannot tell
        forward motion over a flat road from standing still (the road's depth at a pixel
        does not change), and grey level alone cannot tell apart motions over untextured
        walls. Dense, so it counts surfaces rather than keypoints: a textured moving
        object, or a facade of repeated windows matched one period off, can win RANSAC by
        keypoint count, while the static scene covers more of the image. Pixels of ``d``
        found moving when ``d`` itself was placed (:attr:`_moving`) do not vote.

        Returns:
            ``[len(T_0_d)]`` counts of consistent pixels.
        """
        if not T_0_d:
            return np.zeros(0, np.int64)
        inside, consistent = self._consistency(p, d, 0, T_0_d, exclude=self._moving.get(p.views[d].key))
        # only pixels every hypothesis keeps in view vote: the road just below a camera that
        # moves forward leaves the image, and would otherwise count for standing still only
        return np.count_nonzero(consistent & inside.all(axis=0), axis=1).astype(np.int64)

    def _consistency(self, p: _Pass, a: int, b: int, T_b_a: Sequence[np.ndarray],
                     exclude: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """View ``a``'s prior depth pixels on the ``vote_stride`` grid, moved into view ``b``
        by each ``T_b_a[h]``: ``(inside, consistent)``, both ``[len(T_b_a), n_grid]`` bool.

        ``inside``: in front of ``b`` and within its image; ``consistent``: also ``b``'s prior
        depth there within ``vote_depth_tol`` (relative) and its grey level (both images
        blurred with ``vote_blur_sigma``) within ``vote_grey_tol``. Grid pixels without a
        prior depth, or set in ``exclude`` (``[n_grid]`` bool), are neither."""
        import cv2

        c = self.conf
        Da = np.asarray(p.views[a].depth_m, np.float64)
        Db = np.asarray(p.views[b].depth_m, np.float64)
        st = max(int(c["vote_stride"]), 1)
        sigma = float(c["vote_blur_sigma"])
        grey = [cv2.GaussianBlur(grey_image(p.views[k].image), (0, 0), sigma) if sigma > 0
                else grey_image(p.views[k].image) for k in (a, b)]
        H, W = p.feats[a].image_hw
        Hb, Wb = p.feats[b].image_hw
        hb, wb = Db.shape
        vv, uu = np.mgrid[st // 2:H:st, st // 2:W:st]
        vv, uu = vv.ravel(), uu.ravel()
        z = Da[_map_index(vv.astype(np.float64), Da.shape[0], H), _map_index(uu.astype(np.float64), Da.shape[1], W)]
        ok = np.isfinite(z) & (z > 0)
        if exclude is not None and exclude.shape == ok.shape:
            ok &= ~exclude
        sel = np.flatnonzero(ok)
        uv = np.column_stack([uu[sel], vv[sel]]).astype(np.float64)
        g_a = grey[0][vv[sel], uu[sel]]
        X = pixels_to_rays(uv, p.Ks[a]) * z[sel, None]
        inside = np.zeros((len(T_b_a), len(ok)), bool)
        consistent = np.zeros((len(T_b_a), len(ok)), bool)
        g_b = grey[1]
        for h, T in enumerate(T_b_a):
            Xb = X @ T[:3, :3].T + T[:3, 3]
            with np.errstate(divide="ignore", invalid="ignore"):
                pr = Xb @ p.Ks[b].T
                ub, vb = pr[:, 0] / pr[:, 2], pr[:, 1] / pr[:, 2]
            ins = (Xb[:, 2] > 0) & (ub >= 0) & (ub <= Wb - 1) & (vb >= 0) & (vb <= Hb - 1)
            inside[h, sel] = ins
            ub, vb, zi, gi = ub[ins], vb[ins], Xb[ins, 2], g_a[ins]
            meas = Db[_map_index(vb, hb, Hb), _map_index(ub, wb, Wb)]
            x0, y0 = np.minimum(ub.astype(np.int64), Wb - 2), np.minimum(vb.astype(np.int64), Hb - 2)
            ax, ay = ub - x0, vb - y0
            g = ((1 - ax) * (1 - ay) * g_b[y0, x0] + ax * (1 - ay) * g_b[y0, x0 + 1]
                 + (1 - ax) * ay * g_b[y0 + 1, x0] + ax * ay * g_b[y0 + 1, x0 + 1])
            with np.errstate(divide="ignore", invalid="ignore"):
                depth_ok = np.isfinite(meas) & (meas > 0) & (np.abs(zi - meas) <= c["vote_depth_tol"] * meas)
            consistent[h, sel[ins]] = depth_ok & (np.abs(g - gi) <= c["vote_grey_tol"])
        return inside, consistent

    def _note_moving(self, p: _Pass, d: int, T_d_0: np.ndarray) -> None:
        """Remember which of the current view's grid pixels the chosen motion does not
        explain against its depth-prior view ``d`` (a moving object, most of them), so that
        they do not vote when the current view is the prior of the next pass."""
        if not self.conf["mask_moving"] or p.views[0].depth_m is None:
            return
        inside, consistent = self._consistency(p, 0, d, [T_d_0])
        self._moving[p.views[0].key] = inside[0] & ~consistent[0]
        while len(self._moving) > int(self.conf["match_cache_size"]):
            self._moving.popitem(last=False)

    def _place_pnp(self, p: _Pass, s: int, anchors: Sequence[int], rec: _Recon,
                   min_inliers: int | None = None, hypotheses: int = 1, ref_depth: int | None = None,
                   px: float | None = None, priors: Sequence[np.ndarray] = ()) -> bool:
        """Absolute pose of view ``s`` from 2D-3D correspondences through its matches with
        the placed ``anchors``; writes ``rec.T[s]`` and ``rec.obs[s]`` on success (at least
        ``min_inliers`` inliers, default ``conf['min_pnp_inliers']``).

        With ``hypotheses > 1`` RANSAC runs again on the outliers of the previous runs
        (another rigid motion: a moving object, or the static scene when the object won).
        When both ``s`` (must be view 0) and ``ref_depth`` carry depth priors, the hypothesis
        under which most of ``ref_depth``'s pixels land on consistent depth and grey level
        is kept (:meth:`_motion_votes`); otherwise the one with most inliers. ``priors``
        (poses ``T_s_frame``, e.g. the previous motion) join the vote as further
        hypotheses, refined on the correspondences they explain: a moving object that
        holds most keypoints can take every RANSAC round, and then the static scene is
        not among the hypotheses at all."""
        import poselib

        cand_kp, cand_pt = [], []
        for a in anchors:
            if a == s or a not in rec.obs:
                continue
            m = self._m(p, a, s)
            pt = rec.kp_to_pt(a, p.feats[a].n)[m[:, 0]]
            cand_kp.append(m[pt >= 0, 1])
            cand_pt.append(pt[pt >= 0])
        if not cand_kp:
            return False
        kp = np.concatenate(cand_kp)
        pt = np.concatenate(cand_pt)
        _, first = np.unique(kp, return_index=True)  # one 3D point per keypoint of view s
        kp, pt = kp[first], pt[first]
        need = int(self.conf["min_pnp_inliers"] if min_inliers is None else min_inliers)
        if len(kp) < need:
            return False
        uv = p.feats[s].keypoints[kp].astype(np.float64)
        hyps: list[tuple[np.ndarray, np.ndarray]] = []
        left = np.ones(len(kp), bool)
        for _ in range(max(int(hypotheses), 1)):
            if left.sum() < need:
                break
            idx = np.flatnonzero(left)
            pose, info = poselib.estimate_absolute_pose(
                uv[idx], rec.X[pt[idx]], p.cams[s],
                self._ransac(max_reproj_error=float(self.conf["pnp_px"] if px is None else px)), {})
            inl_sub = np.asarray(info["inliers"], bool)
            T_h = _pose_to_T(pose.R, pose.t)
            if inl_sub.sum() < need or not np.all(np.isfinite(T_h)):
                break
            inl_h = np.zeros(len(kp), bool)
            inl_h[idx[inl_sub]] = True
            hyps.append((T_h, inl_h))
            left &= ~inl_h
        rpx = float(self.conf["pnp_px"] if px is None else px)
        for T_prior in priors:
            h = self._prior_hypothesis(uv, rec.X[pt], p.cams[s], p.Ks[s], T_prior, rpx, need)
            if h is not None:
                hyps.append(h)
        if not hyps:
            return False
        T_s_f, inl = hyps[0]
        if len(hyps) > 1 and s == 0 and ref_depth is not None and p.views[0].depth_m is not None:
            # rec's frame is camera ref_depth here, so each T_h maps ref_depth's points into view 0
            votes = self._motion_votes(p, ref_depth, [T_h for T_h, _ in hyps])
            for k, T_d_k in self._chained_views(p, ref_depth):
                votes = votes + self._motion_votes(p, k, [T_h @ T_d_k for T_h, _ in hyps])
            T_s_f, inl = hyps[int(np.argmax(votes))]
        rec.T[s] = _inv(T_s_f)
        rec.obs[s] = (pt[inl], kp[inl])
        return True

    def _chained_views(self, p: _Pass, d: int) -> list[tuple[int, np.ndarray]]:
        """Other views of the pass with a depth prior whose pose relative to view ``d`` the
        stored motions give: ``[(k, T_d_k)]``, at most ``conf['vote_views']``.

        Each placed view's motion relative to its anchor is kept (``_motions``); following
        the anchors from ``d`` back reaches older keyframes. Their votes let the static
        scene outvote an object that moved with the camera since the last frame: such an
        object agrees with a wrong motion in the newest frame only, not in frames that
        were placed on the static scene before."""
        want = int(self.conf["vote_views"])
        if want <= 0:
            return []
        index = {p.views[k].key: k for k in range(1, len(p.views))
                 if k != d and p.views[k].depth_m is not None and not p.low_tex[k]}
        out: list[tuple[int, np.ndarray]] = []
        key, T_d_key = p.views[d].key, np.eye(4)
        for _ in range(int(self.conf["vote_chain_hops"])):
            step = self._motions.get(key)
            if step is None:
                break
            key, T_key_anchor = step
            T_d_key = T_d_key @ T_key_anchor
            if key in index:
                out.append((index[key], T_d_key.copy()))
                if len(out) >= want:
                    break
        return out

    @staticmethod
    def _prior_hypothesis(uv: np.ndarray, X: np.ndarray, cam: dict, K: np.ndarray, T_prior: np.ndarray,
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
        T = _pose_to_T(pose.R, pose.t)
        inl = inliers(T, px) if np.all(np.isfinite(T)) else np.zeros(len(uv), bool)
        return (T, inl) if inl.sum() >= need else None

    def _two_view_with_scale(self, p: _Pass, s: int, rec: _Recon) -> str:
        """Place view ``s`` by its essential matrix with view 0 (placed); scale from shared points.

        Writes ``rec.T[s]`` and the view's observations on success; returns ``""`` or a reason.
        """
        m0s = self._m(p, 0, s)
        uv0 = p.feats[0].keypoints[m0s[:, 0]]
        uvs = p.feats[s].keypoints[m0s[:, 1]]
        T_s_0, inl, why = self._pair_pose(p, 0, s)
        if T_s_0 is None:
            return why
        cur_to_pt = rec.kp_to_pt(0, p.feats[0].n)
        shared = inl & (cur_to_pt[m0s[:, 0]] >= 0)
        if shared.sum() < self.conf["min_scale_points"]:
            return self._two_view_prior_scale(p, s, rec, m0s, inl, T_s_0)
        X_unit, keep, _, _ = self._triangulate_pair(uv0[shared], uvs[shared], p.Ks[0], p.Ks[s], T_s_0)
        pt = cur_to_pt[m0s[shared, 0]]
        if keep.sum() < self.conf["min_scale_points"]:
            return "no-parallax"
        T_0_f = _inv(rec.T[0])
        X0 = rec.X[pt[keep]] @ T_0_f[:3, :3].T + T_0_f[:3, 3]  # shared points in camera 0
        scale = float(np.median(X0[:, 2] / X_unit[keep, 2]))
        if not np.isfinite(scale) or scale <= 0:
            return "few-3d-points"
        T_s_0 = T_s_0.copy()
        T_s_0[:3, 3] *= scale
        rec.T[s] = rec.T[0] @ _inv(T_s_0)
        rec.obs[s] = (pt[keep], m0s[shared, 1][keep])
        return ""

    def _two_view_prior_scale(self, p: _Pass, s: int, rec: _Recon, m0s: np.ndarray, inl: np.ndarray,
                              T_s_0: np.ndarray) -> str:
        """Scale of a unit two-view pose with view 0 from view 0's own depth prior at the
        triangulated inliers (too few points shared with the reconstruction); metric frames only."""
        if p.views[0].depth_m is None or not rec.metric:
            return "few-3d-points"
        uv0 = p.feats[0].keypoints[m0s[inl, 0]]
        uvs = p.feats[s].keypoints[m0s[inl, 1]]
        X_unit, keep, _, _ = self._triangulate_pair(uv0, uvs, p.Ks[0], p.Ks[s], T_s_0)
        z = keypoint_depths(uv0, p.views[0].depth_m, p.feats[0].image_hw, float(self.conf["depth_edge_tol"]))
        keep &= z > 0
        if keep.sum() < self.conf["min_scale_points"]:
            return "few-3d-points"
        scale = float(np.median(z[keep] / X_unit[keep, 2]))
        if not np.isfinite(scale) or scale <= 0:
            return "few-3d-points"
        T = T_s_0.copy()
        T[:3, 3] *= scale
        rec.T[s] = rec.T[0] @ _inv(T)
        return ""

    # ------------------------------------------------------------------ main entry
    def infer(self, views: Sequence[View]) -> BackboneOutput:
        """One joint pass; see the module docstring for the method and the reasons."""
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
        p = _Pass(views=views, feats=feats, Ks=[i.K for i in intr], cams=[_camera(i) for i in intr],
                  low_tex=[f.grey_std < self.conf["min_texture_std"] for f in feats], timings=timings)
        rec, reasons = self._solve(p, timings)
        T = np.full((S, 4, 4), np.nan)
        valid = np.zeros(S, bool)
        valid[0] = True
        if rec is None:
            T[0] = np.eye(4)
        else:
            for s, Ts in rec.T.items():
                T[s] = Ts
                valid[s] = True
        depth, conf = self._depth_maps(p, rec, valid)
        timings["total"] = time.perf_counter() - t0
        reference = rec.pair[1] if rec is not None and rec.metric and rec.pair[1] != 0 else None
        return BackboneOutput(T_frame_cam=T, valid=valid, depth=depth, depth_conf=conf,
                              intrinsics=list(intr), reasons=reasons, timings_s=timings,
                              metric_unit=rec is not None and rec.metric, reference=reference)

    def _solve(self, p: _Pass, timings: dict[str, float]) -> tuple[_Recon | None, list[str]]:
        """The reconstruction of this pass (None: nothing placed besides view 0) and reasons.

        The depth-anchored reconstruction comes first. When it leaves out a view that shares
        enough matches with the current one, the image-only one is built too, and the views
        only it placed join the depth one (:meth:`_merge_image_only`) when the two agree on
        the views both placed; so a prior never costs a direct estimate that the images
        support, and an image-only pass never replaces the metric one (its two-view poses
        over forward motion are off by a degree or more: 50 cm of ego error per step on
        CAD). Without a depth reconstruction, the image-only one is the pass."""
        S = len(p.views)
        if S == 1:
            return None, [""]
        if p.low_tex[0] or p.feats[0].n < self.conf["min_matches"]:
            return None, [""] + ["low-texture" if p.low_tex[0] else "few-matches"] * (S - 1)
        if not self.conf["depth_prior"]:
            return self._solve_once(p, timings, metric=False)
        rec, reasons = self._solve_once(p, timings, metric=True)
        if rec is not None and not self._retry_image_only(p, rec):
            return rec, reasons
        rec_i, reasons_i = self._solve_once(p, timings, metric=False)
        if rec is None:
            # nothing placed either way: the image-only attempt's reasons say more (parallax, texture)
            return rec_i, reasons_i
        if rec_i is not None:
            for s in self._merge_image_only(rec, rec_i, float(p.Ks[0][0, 0])):
                reasons[s] = ""
        return rec, reasons

    def _merge_image_only(self, rec: _Recon, rec_i: _Recon, focal_px: float) -> list[int]:
        """Add to the metric ``rec`` the views that only the image-only ``rec_i`` placed.

        Both frames are the current camera's. ``rec_i``'s unit is set by the ratio of the
        translations of the views both placed (those at least ``merge_min_baseline_m`` away),
        and nothing is added unless the two agree on those views: rotations within
        ``merge_max_rot_px`` pixels at the current view's focal length ``focal_px`` (what
        two-view geometry can resolve depends on it), translation directions within
        ``merge_max_dir_deg``,
        ratios within a factor ``merge_max_ratio_spread``. Each added view brings its
        observed points of ``rec_i``, scaled. Returns the added view indices."""
        c = self.conf
        extra = [s for s in rec_i.T if s not in rec.T]
        common = [s for s in rec.T if s in rec_i.T and s != 0]
        ratios = []
        for s in common:
            Tm, Ti = rec.T[s], rec_i.T[s]
            cos = (np.trace(Tm[:3, :3].T @ Ti[:3, :3]) - 1.0) / 2.0
            if np.arccos(np.clip(cos, -1.0, 1.0)) * focal_px > c["merge_max_rot_px"]:
                self.n_merge_refused["rotation"] += 1
                return []
            tm, ti = Tm[:3, 3], Ti[:3, 3]
            nm, ni = float(np.linalg.norm(tm)), float(np.linalg.norm(ti))
            if nm < c["merge_min_baseline_m"] or ni <= 0:
                continue
            if np.degrees(np.arccos(np.clip(tm @ ti / (nm * ni), -1.0, 1.0))) > c["merge_max_dir_deg"]:
                self.n_merge_refused["direction"] += 1
                return []
            ratios.append(nm / ni)
        if not extra:
            return []
        if not ratios or max(ratios) > c["merge_max_ratio_spread"] * min(ratios):
            reason = "no-baseline" if not ratios else "scale"
            self.n_merge_refused[reason] += 1
            return []
        scale = float(np.median(ratios))
        for s in extra:
            T = rec_i.T[s].copy()
            T[:3, 3] *= scale
            ids, kp = rec_i.obs[s]
            new = np.arange(len(rec.X), len(rec.X) + len(ids))
            rec.X = np.vstack([rec.X, rec_i.X[ids] * scale])
            rec.T[s], rec.obs[s] = T, (new, kp)
        self.n_merged += len(extra)
        return extra

    def _retry_image_only(self, p: _Pass, rec: _Recon) -> bool:
        """Whether the image-only solve could place a view ``rec`` left out: one with at
        least ``min_pnp_inliers`` matches with the current view (the 2D-3D correspondences
        an absolute pose needs come mostly through them). A collaborator image the gate let
        through without overlap has fewer, and re-solving for it would only double the
        pass's cost."""
        need = int(self.conf["min_pnp_inliers"])
        return any(s not in rec.T and not p.low_tex[s] and len(self._m(p, 0, s)) >= need
                   for s in range(1, len(p.views)))

    def _solve_once(self, p: _Pass, timings: dict[str, float], metric: bool) -> tuple[_Recon | None, list[str]]:
        S = len(p.views)
        reasons = [""] + ["no-reference"] * (S - 1)
        tg = time.perf_counter()
        rec, why = self._bootstrap_depth(p) if metric else self._bootstrap(p, 0, range(1, S))
        timings["two_view"] = timings.get("two_view", 0.0) + time.perf_counter() - tg
        if rec is None:
            return None, [""] + [why.get(s) or "no-reference" for s in range(1, S)]
        tp = time.perf_counter()
        anchors = (0,) + tuple(a for a in rec.pair if a != 0)[:1]
        for s in range(1, S):
            if s in rec.T:
                continue
            if p.low_tex[s]:
                reasons[s] = "low-texture"
            elif not self._place_pnp(p, s, anchors, rec):
                reasons[s] = self._two_view_with_scale(p, s, rec)
                reasons[s] = (why.get(s) or reasons[s]) if reasons[s] else ""
        for s in rec.T:
            reasons[s] = ""
        timings["pnp"] = timings.get("pnp", 0.0) + time.perf_counter() - tp
        return rec, reasons

    def _depth_maps(self, p: _Pass, rec: _Recon | None, valid: np.ndarray
                    ) -> tuple[list[np.ndarray], list[np.ndarray]]:
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
            Tsf = _inv(rec.T[s])
            Xs = rec.X[ids] @ Tsf[:3, :3].T + Tsf[:3, 3]
            uv = p.feats[s].keypoints[kp]
            err = reprojection_error(Xs, uv, p.Ks[s])
            depth[s], conf[s] = splat_depth(uv, Xs[:, 2], n_obs[ids] / (1.0 + np.minimum(err, 1e3)), hw[s])
        return depth, conf
