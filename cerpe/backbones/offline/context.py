"""What one pass of the offline backbone works on, and the memo it hands back about its current view.

:class:`Pass` bundles the views of one ``infer`` call with their features, intrinsics,
cached matches, configuration and counters; :class:`Recon` is a reconstruction
(points and placed views). The backbone keeps nothing about a robot between calls:
what a later pass needs about the current view once it is a keyframe or the
previous frame leaves in its memo (``BackboneOutput.memos[0]``) and comes back as
``View.memo``:

* ``image``: the view's content key, checked on the way back (a memo handed back
  with other pixels is an error, not a silently wrong prior);
* ``chain``: the motion that placed the view on its depth-prior view, then the one
  that placed that view on its own, ...: ``((anchor key, T_view_anchor), ...)``,
  newest first, at most :data:`VOTE_CHAIN_HOPS` hops. The first hop is
  the constant-velocity prior; the chain reaches older keyframes that vote too;
* ``moving``: ``[n_grid] bool`` vote-grid pixels of the view that its motion did not
  explain (a moving object), or None;
* ``log_scale`` (optional): ``(a, m)``, the view's prior's log depth scale in the robot's
  running reference and the running mean of its recent frames (:mod:`.framescale`), or
  None (no per-frame scale kept: a depth sensor's prior, or none measured).
"""
from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Callable, Hashable, Mapping, Sequence

import numpy as np

from ...protocols import BackboneError, View
from ..cache import LRUCache, content_key
from ..config import OfflineConfig
from ..xfeat import XFeatFeatures
from .matching import PairMatcher, match_mnn

MEMO_FIELDS = ("image", "chain", "moving")
# hops of a memo's motion chain: how far back older views can still vote (:func:`.vote.chained_views`)
VOTE_CHAIN_HOPS = 12
# poselib's least RANSAC iterations (its default costs a pair without overlap far more than the
# inlier ratios of overlapping frames need); the most: OfflineConfig.ransac_max_iterations
RANSAC_MIN_ITERATIONS = 100
P3P_SAMPLE = 3  # 2D-3D pairs of P3P's minimal sample
FIVE_POINT_SAMPLE = 5  # image pairs of the essential matrix's minimal sample
# the depth-prior views a pass may anchor on are ranked by their matches among the RANK_KEYPOINTS best
# keypoints of each view (Pass.shared_estimate); the first RANK_FULL of them by their full matches
RANK_KEYPOINTS = 512
RANK_FULL = 2

Chain = tuple[tuple[Hashable, np.ndarray], ...]


class OfflineBackboneError(BackboneError):
    """A view the offline backbone cannot take at all (no intrinsics, malformed image, a foreign memo)."""


@dataclass
class Recon:
    """Points and placed views of one reconstruction (frame: its anchor view's camera).

    Attributes:
        X: ``[P,3]`` points in the frame.
        T: view index -> ``T_frame_view [4,4]`` (metric up to the pass's unit).
        obs: view index -> ``(point ids [M], keypoint ids [M])`` of that view.
        pair: the two views that made the points (anchor first).
        metric: the unit is the metre (the points came from a depth prior).
    """

    X: np.ndarray
    T: dict[int, np.ndarray] = field(default_factory=dict)
    obs: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    pair: tuple[int, int] = (0, 0)
    metric: bool = False

    def kp_to_pt(self, s: int, n_kp: int) -> np.ndarray:
        """``[n_kp]`` point id of each keypoint of view ``s`` (-1: none)."""
        a = np.full(n_kp, -1, np.int64)
        if s in self.obs:
            ids, kp = self.obs[s]
            a[kp] = ids
        return a


def check_memo(view: View, s: int, feats: XFeatFeatures) -> Mapping[str, Any] | None:
    """``view.memo`` when it is this backbone's memo of these pixels, None when there is none.

    Raises:
        OfflineBackboneError: a memo of another backbone or of another image.
    """
    memo = view.memo
    if memo is None:
        return None
    if not isinstance(memo, Mapping) or any(k not in memo for k in MEMO_FIELDS):
        raise OfflineBackboneError(f"offline backbone: view {s} (key {view.key!r}) carries a memo that is not "
                                   f"this backbone's (fields {', '.join(MEMO_FIELDS)})")
    if memo["image"] != feats.fingerprint:
        raise OfflineBackboneError(f"offline backbone: view {s} (key {view.key!r}) carries the memo of "
                                   f"another image")
    return memo


def iterations_to_find(inliers: int, points: int, sample: int) -> int:
    """RANSAC iterations after which poselib stops once it holds a model with ``inliers`` of ``points``:
    its own rule, ``dyn_num_trials_mult * log(1 - success_prob) / log(1 - w ** sample)`` with
    ``w = inliers / points`` and poselib's defaults. A better model stops it sooner, so a search that
    keeps only such models gains nothing from more: a failing search (the second motion hypothesis on
    the first one's outliers, mostly) no longer runs to the iteration bound."""
    import poselib

    w = min(max(inliers, 0) / max(points, 1), 1.0)
    if w >= 1.0:
        return 1
    if w <= 0.0:
        return 2**31 - 1
    o = poselib.RansacOptions()
    n = np.log(1.0 - o["success_prob"]) / np.log1p(-(w ** sample)) * o["dyn_num_trials_mult"]
    return int(min(np.ceil(n), 2**31 - 1))


def bounded(ransac: dict[str, float], inliers: int, points: int, sample: int) -> dict[str, float]:
    """``ransac`` (poselib options) with ``max_iterations`` lowered to :func:`iterations_to_find`,
    never below its ``min_iterations``."""
    most = min(int(ransac["max_iterations"]), iterations_to_find(inliers, points, sample))
    return {**ransac, "max_iterations": max(most, int(ransac.get("min_iterations", 0)))}


@dataclass
class Pass:
    """The inputs of one pass, shared by the helpers of the package."""

    views: list[View]  # view 0's prior may be rescaled during the pass (:mod:`.framescale`)
    feats: list[XFeatFeatures]
    Ks: list[np.ndarray | None]  # None: a collaborator view without intrinsics (never registered)
    cams: list[dict | None]
    low_tex: list[bool]
    conf: OfflineConfig
    matcher: PairMatcher
    memos: list[Mapping[str, Any] | None] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    # (a, b) -> essential-matrix result of views a and b (the depth-anchored and the
    # image-only solves of one pass ask for the same pairs)
    relative: dict[tuple[int, int], tuple[np.ndarray | None, np.ndarray, str]] = field(default_factory=dict)
    # events of this pass: "dense-refined", "dense-refused:<reason>", "merged", "merge-refused:<reason>"
    counts: Counter = field(default_factory=Counter)
    memo_out: dict[str, Any] | None = None  # the memo of view 0, once a depth prior placed it
    # per-frame depth scale (:mod:`.framescale`): the pass's reference log scale (None: off) and
    # the current view's (a, m) once measured
    scale_ref: float | None = None
    log_scale_out: tuple[float, float] | None = None
    # blurred grey images by (content key, sigma): the vote, the frame scale and the appearance check
    # read the same ones many times a pass, and a keyframe's again in every later pass
    greys: LRUCache | None = None
    # other arrays derived from one view's pixels or prior alone, by a key naming what and of what
    # (the vote's grid of a prior, the dense alignment's pyramid of an image): a frame's come back
    # when it is the previous frame and a keyframe
    derived_cache: LRUCache | None = None

    def subset(self, idx: Sequence[int]) -> "Pass":
        """A pass over views ``idx`` of this one (same matcher, timings and counters)."""
        return Pass(views=[self.views[s] for s in idx], feats=[self.feats[s] for s in idx],
                    Ks=[self.Ks[s] for s in idx], cams=[self.cams[s] for s in idx],
                    low_tex=[self.low_tex[s] for s in idx], conf=self.conf, matcher=self.matcher,
                    memos=[self.memos[s] for s in idx], timings=self.timings, counts=self.counts,
                    scale_ref=self.scale_ref, greys=self.greys, derived_cache=self.derived_cache)

    def prior_key(self, k: int, with_depth: bool = True) -> tuple:
        """What identifies view ``k``'s geometry for :meth:`derived`: image size, intrinsics and the
        content key of its depth prior (None without one, or without ``with_depth``)."""
        depth = self.views[k].depth_m if with_depth else None
        return (self.feats[k].image_hw, np.asarray(self.Ks[k], np.float64).tobytes(),
                None if depth is None else content_key(depth))

    def derived(self, key: Hashable, make: Callable[[], Any]) -> Any:
        """``make()``, cached under ``key`` (:attr:`derived_cache`); ``key`` must name all ``make`` reads."""
        if self.derived_cache is None:
            return make()
        out = self.derived_cache.get(key)
        if out is None:
            out = make()
            self.derived_cache.put(key, out)
        return out

    def grey(self, k: int, sigma: float) -> np.ndarray:
        """``[H,W] float32`` grey image of view ``k`` blurred with ``sigma`` px (none at 0), read-only;
        cached by the view's content key."""
        import cv2

        from ..rgbd_align import grey_image

        key = (self.feats[k].fingerprint, float(sigma)) if k < len(self.feats) and self.feats[k].fingerprint else None
        g = self.greys.get(key) if key is not None and self.greys is not None else None
        if g is None:
            g = grey_image(self.views[k].image)
            if sigma > 0:
                g = cv2.GaussianBlur(g, (0, 0), float(sigma))
            g.setflags(write=False)
            if key is not None and self.greys is not None:
                self.greys.put(key, g)
        return g

    def m(self, a: int, b: int) -> np.ndarray:
        """``[M,2]`` keypoint index pairs between views ``a`` and ``b`` (empty for low texture)."""
        if self.low_tex[a] or self.low_tex[b]:
            return np.zeros((0, 2), np.int64)
        if "collaborator" in (self.views[a].role, self.views[b].role):
            return self.matcher(self.feats[a], self.feats[b])  # timed as part of "cross"
        t0 = time.perf_counter()
        try:
            return self.matcher(self.feats[a], self.feats[b])
        finally:
            self.timings["match"] = self.timings.get("match", 0.0) + time.perf_counter() - t0

    def rank_by_shared(self, a: int, cands: Sequence[int]) -> list[int]:
        """``cands`` by the matches they share with view ``a``, most first (stable). All are ranked by
        :meth:`shared_estimate`; the first :data:`RANK_FULL` of them then by their full matches, which
        only the view the pass anchors on needs: one full match is sixteen estimates."""
        est = sorted(cands, key=lambda d: -self.shared_estimate(a, d)) if len(cands) > RANK_FULL else list(cands)
        head = sorted(est[:RANK_FULL], key=lambda d: -len(self.m(a, d)))
        return head + est[RANK_FULL:]

    def shared_estimate(self, a: int, b: int) -> int:
        """Matches of views ``a`` and ``b`` among their :data:`RANK_KEYPOINTS` best keypoints each (a
        view's features sort by score), with the thresholds of the full match."""
        if self.low_tex[a] or self.low_tex[b]:
            return 0
        t0 = time.perf_counter()
        try:
            n = RANK_KEYPOINTS
            return len(match_mnn(self.feats[a].descriptors[:n], self.feats[b].descriptors[:n],
                                 self.matcher.min_cossim, self.matcher.ratio))
        finally:
            self.timings["match"] = self.timings.get("match", 0.0) + time.perf_counter() - t0

    def ransac(self, need: tuple[int, int, int] | None = None, **extra: float) -> dict[str, float]:
        """poselib RANSAC options with this pass's iteration bounds. ``need = (inliers, points, sample)``:
        a model is kept only with at least ``inliers`` of ``points`` (minimal sample ``sample``), so the
        iterations stop where poselib would stop had it found one (:func:`iterations_to_find`)."""
        opts = {"min_iterations": RANSAC_MIN_ITERATIONS, "max_iterations": self.conf.ransac_max_iterations, **extra}
        return opts if need is None else bounded(opts, *need)

    def chain(self, k: int) -> Chain:
        """The motion chain of view ``k`` from its memo (empty without one)."""
        memo = self.memos[k] if k < len(self.memos) else None
        return tuple(memo["chain"]) if memo is not None else ()

    def moving(self, k: int) -> np.ndarray | None:
        """The moving-pixel grid mask of view ``k`` from its memo (None without one)."""
        memo = self.memos[k] if k < len(self.memos) else None
        return None if memo is None or memo["moving"] is None else np.asarray(memo["moving"], bool)

    def remember(self, d: int, T_cur_d: np.ndarray, moving: np.ndarray | None) -> None:
        """Set the memo of view 0, placed on view ``d`` by ``T_cur_d`` (camera-``d`` points
        into the current camera), with its moving-pixel mask."""
        T = np.array(T_cur_d, np.float64)
        T.setflags(write=False)
        if moving is not None:
            moving = np.array(moving, bool)
            moving.setflags(write=False)
        hops = max(VOTE_CHAIN_HOPS, 1)
        chain = ((self.views[d].key, T),) + self.chain(d)[:hops - 1]
        self.memo_out = {"image": self.feats[0].fingerprint, "chain": chain, "moving": moving,
                         "log_scale": self.log_scale_out}
