"""The offline backbone: classical multi-view geometry behind :class:`cerpe.protocols.PoseBackbone`.

The stand-in for VGGT's joint pass over ``[current] + memory + collaborators``.
It computes XFeat features (cached by content) and mutual-nearest-neighbour matches
(cached by both images' content). Then it builds a metric reconstruction on the views'
depth priors (:mod:`.reconstruction`). An image-only one (:mod:`.two_view`) serves where
no prior anchors, or adds views the metric one left out. Per view: the pose in the current
camera's frame (``T_frame_cam[0] = I``), sparse depth of its inlier points and
confidence ``n_obs / (1 + reprojection error px)``.

Views that cannot be placed are ``valid=False`` with a reason (``few-matches``,
``few-inliers``, ``no-parallax``, ``few-3d-points``, ``few-depth-points``,
``no-reference``, ``low-texture``; ``not-wanted``: the caller did not ask for it,
:attr:`~cerpe.protocols.View.pose_wanted`) and NaN poses. No exception leaves :meth:`infer`
for data reasons; a view without intrinsics, a malformed image or a memo that is
not this backbone's raise :class:`OfflineBackboneError`.

No state between calls: what a later pass needs about the current view goes out in
``BackboneOutput.memos[0]`` (see :mod:`.context`), so a pass depends on its views
(and their memos) alone.
"""
from __future__ import annotations

import dataclasses
import time
from collections import Counter
from typing import Any, Sequence

import numpy as np

from ...geometry import se3_inverse
from ...protocols import BLANK_STD, BackboneOutput, View
from ..cache import LRUCache
from ..config import OfflineConfig
from ..xfeat import ImageInputError, XFeatEncoder, check_image, shared_encoder
from . import cross as cross_mod
from . import framescale
from .context import OfflineBackboneError, Pass, Recon, check_memo
from .matching import MIN_COSSIM, RATIO, PairMatcher, pinhole_camera, reprojection_error, splat_depth
from .reconstruction import MIN_PNP_INLIERS, bootstrap_depth, place_pnp
from .two_view import MIN_MATCHES, bootstrap, merge_image_only, two_view_with_scale


MATCH_CACHE_SIZE = 256  # matched image pairs kept (LRU by both images' content)
GREY_CACHE_SIZE = 48  # blurred grey images kept (LRU by content and blur), about a memory's views at two blurs
MATCH_CACHE_PER_ROBOT = 128  # matched pairs kept per robot when a team shares the backbone (serve_robots)
GREY_CACHE_PER_ROBOT = 24  # blurred grey images kept per robot when a team shares the backbone
DERIVED_CACHE_SIZE = 16  # other per-view arrays kept (Pass.derived: vote grids, dense-alignment pyramids)
DERIVED_CACHE_PER_ROBOT = 8  # ... per robot when a team shares the backbone


class OfflineGeometryBackbone:
    """XFeat + RANSAC + P3P on depth priors + dense refinement; see the module docstring.

    Args:
        conf: the user's settings (:class:`~cerpe.backbones.config.OfflineConfig`: keypoints, inlier
            counts and thresholds, the moving mask, the per-frame depth scale, ``dense`` refinement,
            ``cross`` registration); every other value is a constant of the module that uses it
            (:mod:`.matching`, :mod:`.two_view`, :mod:`.reconstruction`, :mod:`.vote`,
            :mod:`.framescale`, :mod:`.cross`).
        encoder: the shared :class:`XFeatEncoder` (None: :func:`shared_encoder` with
            ``conf.keypoints`` and ``conf.precision``).
        learned: the cross-robot learned matcher to use (default: a :class:`.cross.LearnedMatcher`
            of ``conf.cross``, built on first use).

    ``counts`` accumulates events over passes; they are statistics only and change no result:

    * ``dense-refined``, ``dense-refused:<why>``, ``merged``, ``merge-refused:<why>``;
    * ``cross-registered``, ``cross-none``, ``cross-learned-pairs``, ``cross-unscaled``,
      ``cross-bad-image``, ``cross-image-size-mismatch``;
    * ``cross-learned``: collaborator views the learned stage ran for;
    * ``cross-fallback-placed``, ``cross-fallback-none``: collaborators asked for with
      ``try_hard`` that the joint pass left, placed apart or not;
    * ``cross-appearance-checked``, ``cross-appearance-rejected``.
    """

    def __init__(self, conf: OfflineConfig | None = None, encoder: XFeatEncoder | None = None,
                 learned: Any = None) -> None:
        self.conf = conf or OfflineConfig()
        self.encoder = encoder or shared_encoder(self.conf.keypoints, precision=self.conf.precision)
        self.matcher = PairMatcher(MIN_COSSIM, RATIO, MATCH_CACHE_SIZE)
        self.greys: LRUCache[np.ndarray] = LRUCache(GREY_CACHE_SIZE)
        self.derived: LRUCache = LRUCache(DERIVED_CACHE_SIZE)
        self.counts: Counter[str] = Counter()
        self._learned = learned

    def learned(self) -> Any:
        """The cross-robot learned matcher (loaded on first use)."""
        if self._learned is None:
            self._learned = cross_mod.LearnedMatcher(self.conf.cross)
        return self._learned

    def serve_robots(self, n_robots: int) -> None:
        """``n_robots`` robots of one process share this backbone (a team in one process): its caches
        and the encoder's grow to hold each robot's working set, so that a larger team does not
        recompute what a smaller one finds cached. Results do not change (a hit equals a recomputation)."""
        n = max(int(n_robots), 1)
        self.matcher.cache.reserve(n * MATCH_CACHE_PER_ROBOT)
        self.greys.reserve(n * GREY_CACHE_PER_ROBOT)
        self.derived.reserve(n * DERIVED_CACHE_PER_ROBOT)
        if callable(getattr(self.encoder, "serve_robots", None)):
            self.encoder.serve_robots(n)

    def clear_caches(self) -> None:
        """Forget cached matches and learned features (a cold start; XFeat features live in the encoder's cache)."""
        self.matcher.clear()
        self.greys.clear()
        self.derived.clear()
        if self._learned is not None and callable(getattr(self._learned, "clear_cache", None)):
            self._learned.clear_cache()

    def infer(self, views: Sequence[View]) -> BackboneOutput:
        """One joint pass over ``[current] + keyframes + previous frame + collaborators``.

        With ``cross.enabled``, views whose role is ``"collaborator"`` stay out of the
        own reconstruction and are registered against single own views
        (``BackboneOutput.registrations``). A collaborator without intrinsics is left
        unplaced (``no-intrinsics``) rather than refused, as is one whose image this backbone
        refuses (``bad-image``) or whose size is not its intrinsics' (``image-size-mismatch``)."""
        S = len(views)
        if S == 0:
            raise OfflineBackboneError("offline backbone: no views given")
        cross_on = self._cross_on(views)
        bad = {s: why for s, v in enumerate(views) if s > 0 and v.role == "collaborator"
               and cross_on and (why := self._bad_collaborator(v))}
        if bad:
            return self._infer_without(views, bad)
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        is_collab = [cross_on and s > 0 and v.role == "collaborator"
                     for s, v in enumerate(views)]
        for s, v in enumerate(views):
            if v.intrinsics is None and not is_collab[s]:
                raise OfflineBackboneError(
                    f"offline backbone: view {s} (key {v.key!r}) has no intrinsics; this backbone needs them")
            check_image(v.image, f"view {s} (key {v.key!r})")
        intr = [v.intrinsics for v in views]
        feats = [self.encoder.encode(v) for v in views]
        timings["encode"] = time.perf_counter() - t0
        memos = [None] + [check_memo(v, s, f) for s, (v, f) in enumerate(zip(views, feats)) if s > 0]
        views = list(views)
        scale_ref = None
        if framescale.enabled(views, self.conf):
            scale_ref = framescale.reference_mean(views, memos)
            views = framescale.correct_views(views, memos, scale_ref)
        p = Pass(views=views, feats=feats, Ks=[None if i is None else i.K for i in intr],
                 cams=[None if i is None else pinhole_camera(i) for i in intr],
                 low_tex=[f.grey_std < BLANK_STD for f in feats], conf=self.conf,
                 matcher=self.matcher, memos=memos, timings=timings, scale_ref=scale_ref, greys=self.greys,
                 derived_cache=self.derived)
        own = [s for s in range(S) if not is_collab[s]]
        rec, reasons = self._solve_own(p, own)
        cross_mod.check_joint_placements(p, rec, [s for s in own if views[s].role == "collaborator"], reasons)
        T = np.full((S, 4, 4), np.nan)
        valid = np.zeros(S, bool)
        valid[0] = True
        support = [-1] * S  # the 2D-3D inliers that placed each view (BackboneOutput.support)
        if rec is None:
            T[0] = np.eye(4)
        else:
            for s, Ts in rec.T.items():
                T[s] = Ts
                valid[s] = True
                if s in rec.obs:
                    support[s] = len(rec.obs[s][0])
        collab = [s for s in range(S) if is_collab[s]]
        late = self._fallback(views, valid, cross_on)
        mine = [s for s in own if views[s].role != "collaborator"]
        regs, why = cross_mod.register_collaborators(p, rec, mine, collab + late, self.learned, strict=late)
        cross_mod.place_collaborators(regs, T, valid, support)
        for s in collab:
            # registered only through views this pass did not place: the algorithm composes those itself
            reasons[s] = "" if valid[s] else "via-unplaced" if s in regs else why.get(s, "no-reference")
        for s in late:  # the joint pass's reason stays where the fallback did not place it either
            p.counts["cross-fallback-placed" if valid[s] else "cross-fallback-none"] += 1
            reasons[s] = "" if valid[s] else reasons[s]
        self.counts.update(p.counts)
        depth, conf = _depth_maps(p, rec, valid)
        timings["total"] = time.perf_counter() - t0
        reference = rec.pair[1] if rec is not None and rec.metric and rec.pair[1] != 0 else None
        # a pass that placed only view 0 is in metres when its registrations are (P3P on depth priors)
        metric = rec.metric if rec is not None else bool(regs) and any(views[s].depth_m is not None for s in own)
        return BackboneOutput(T_frame_cam=T, valid=valid, depth=depth, depth_conf=conf,
                              intrinsics=list(intr), reasons=reasons, timings_s=pass_profile(timings),
                              metric_unit=metric, reference=reference,
                              memos=[p.memo_out] + [None] * (S - 1), registrations=regs, support=support,
                              extra={"cross_learned_pairs": float(p.counts["cross-learned-pairs"])})

    def _cross_on(self, views: Sequence[View]) -> bool:
        """Whether this pass registers collaborators apart (``cross.enabled``; ``"without-depth"``:
        when none of the robot's own views has depth)."""
        on = self.conf.cross.enabled
        if on == "without-depth":
            return all(v.depth_m is None for v in views if v.role != "collaborator")
        return bool(on)

    def _fallback(self, views: Sequence[View], valid: np.ndarray, cross_on: bool) -> list[int]:
        """Collaborators of a joint pass (``cross`` off) it left unplaced that the robot asks to try hard
        (``View.try_hard``): registered apart (``cross.fallback``)."""
        if cross_on or not self.conf.cross.fallback:
            return []
        return [s for s, v in enumerate(views) if s > 0 and v.role == "collaborator" and v.try_hard
                and not valid[s] and v.intrinsics is not None]

    def _bad_collaborator(self, v: View) -> str:
        """Why a received view cannot be used at all (``""``: it can): an image this backbone
        refuses (``bad-image``) or one of another size than its intrinsics (``image-size-mismatch``)."""
        try:
            check_image(v.image, f"view {v.key!r}")
        except ImageInputError:
            return "bad-image"
        i = v.intrinsics
        if i is not None and tuple(v.image.shape[:2]) != (int(i.height), int(i.width)):
            return "image-size-mismatch"
        return ""

    def _infer_without(self, views: Sequence[View], bad: dict[int, str]) -> BackboneOutput:
        """The pass without the unusable collaborator views ``bad`` (index -> reason), which come
        back unplaced with their reason (counted ``cross-<reason>``), the indices of the others kept."""
        keep = [s for s in range(len(views)) if s not in bad]
        new = {s: i for i, s in enumerate(keep)}
        out = self.infer([views[s] for s in keep])
        self.counts.update(f"cross-{why}" for why in bad.values())
        S = len(views)
        T = np.full((S, 4, 4), np.nan)
        T[keep] = out.T_frame_cam
        valid = np.zeros(S, bool)
        valid[keep] = out.valid
        def pick(xs: list, fill: Any) -> list:
            return [xs[new[s]] if s in new else fill(views[s]) for s in range(S)]

        def empty(v: View) -> np.ndarray:
            shape = getattr(v.image, "shape", ())
            return np.zeros(tuple(shape[:2]) if len(shape) >= 2 else (0, 0), np.float32)

        regs = {keep[k]: [dataclasses.replace(r, via=keep[r.via]) for r in rs] for k, rs in out.registrations.items()}
        return dataclasses.replace(
            out, T_frame_cam=T, valid=valid, depth=pick(out.depth, empty), depth_conf=pick(out.depth_conf, empty),
            intrinsics=pick(out.intrinsics, lambda v: v.intrinsics), reasons=[bad.get(s) or out.reasons[new[s]] for s in range(S)],
            memos=pick(out.memos, lambda v: None) if out.memos else [], registrations=regs,
            support=pick(out.support, lambda v: -1), reference=None if out.reference is None else keep[out.reference])

    def _solve_own(self, p: Pass, own: list[int]) -> tuple[Recon | None, list[str]]:
        """:meth:`_solve` over the own views ``own`` (all views when there is no collaborator),
        the reconstruction and reasons given with the indices of ``p``."""
        S = len(p.views)
        if len(own) == S:
            return self._solve(p)
        sub = p.subset(own)
        rec, sub_reasons = self._solve(sub)
        p.memo_out = sub.memo_out
        p.views[0] = sub.views[0]  # its prior, rescaled to the pass's scale (:mod:`.framescale`)
        reasons = [""] * S
        for i, s in enumerate(own):
            reasons[s] = sub_reasons[i]
        if rec is not None:
            rec = Recon(X=rec.X, T={own[i]: T for i, T in rec.T.items()},
                        obs={own[i]: o for i, o in rec.obs.items()}, pair=(own[rec.pair[0]], own[rec.pair[1]]),
                        metric=rec.metric)
        return rec, reasons

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
        if p.low_tex[0] or p.feats[0].n < MIN_MATCHES:
            return None, [""] + ["low-texture" if p.low_tex[0] else "few-matches"] * (S - 1)
        rec, reasons = _solve_once(p, metric=True)
        if rec is not None and not _retry_image_only(p, rec, _unwanted(p, rec)):
            return rec, reasons
        rec_i, reasons_i = _solve_once(p, metric=False)
        if rec is None:
            # nothing placed either way: the image-only attempt's reasons say more (parallax, texture)
            return rec_i, reasons_i
        if rec_i is not None:
            for s in merge_image_only(rec, rec_i, float(p.Ks[0][0, 0]), p.counts):
                reasons[s] = ""
        return rec, reasons


#: disjoint parts of a pass's wall time (BackboneOutput.timings_s, seconds), besides "pose" (P3P,
#: two-view geometry and the rest: what the others leave of "total"): XFeat (a view cached before costs its hash),
#: mutual-NN matching of own views, the motion vote and moving mask, the dense RGB-D refinement, and the
#: registration of collaborators apart from the joint pass (its matching included)
PASS_PARTS = ("encode", "match", "vote", "dense", "cross")


def pass_profile(timings: dict[str, float]) -> dict[str, float]:
    """:data:`PASS_PARTS`, ``pose`` and ``total`` of a pass's raw timers (seconds)."""
    out = {k: float(timings.get(k, 0.0)) for k in PASS_PARTS}
    total = float(timings.get("total", 0.0))
    out["pose"] = max(total - sum(out.values()), 0.0)
    out["total"] = total
    return out


def _retry_image_only(p: Pass, rec: Recon, unwanted: set[int]) -> bool:
    """Whether the image-only solve could place a view ``rec`` left out (``unwanted`` ones aside): one
    with at least :data:`.reconstruction.MIN_PNP_INLIERS` matches with the current view. A collaborator
    image without overlap has fewer, and re-solving for it would only double the pass's cost."""
    need = MIN_PNP_INLIERS
    return any(s not in rec.T and s not in unwanted and not p.low_tex[s] and len(p.m(0, s)) >= need
               for s in range(1, len(p.views)))


def _unwanted(p: Pass, rec: Recon) -> set[int]:
    """Views the pass need not place (:attr:`View.pose_wanted` False): only in a metric pass whose
    reference is another view than the current one, since the caller then reads that one alone."""
    if not rec.metric or rec.pair[1] == 0:
        return set()
    return {s for s in range(1, len(p.views)) if not p.views[s].pose_wanted and s != rec.pair[1]}


def _solve_once(p: Pass, metric: bool) -> tuple[Recon | None, list[str]]:
    """One reconstruction (metric: on a depth prior; else image-only) and every view placed on it."""
    S = len(p.views)
    reasons = [""] + ["no-reference"] * (S - 1)
    rec, why = bootstrap_depth(p) if metric else bootstrap(p, 0, range(1, S))
    if rec is None:
        return None, [""] + [why.get(s) or "no-reference" for s in range(1, S)]
    anchors = (0,) + tuple(a for a in rec.pair if a != 0)[:1]
    unwanted = _unwanted(p, rec)
    for s in range(1, S):
        if s in rec.T:
            continue
        if s in unwanted:
            reasons[s] = "not-wanted"
        elif p.low_tex[s]:
            reasons[s] = "low-texture"
        elif not place_pnp(p, s, anchors, rec):
            reasons[s] = two_view_with_scale(p, s, rec)
            reasons[s] = (why.get(s) or reasons[s]) if reasons[s] else ""
    for s in rec.T:
        reasons[s] = ""
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
