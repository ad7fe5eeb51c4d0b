"""Cross-robot registration: each collaborator view against the robot's own views.

A collaborator view ``k`` (``View.role == "collaborator"``) is placed against single own
views, never inside the own reconstruction:

* with depth priors: against every own view that has one (current, previous frame,
  keyframes) by P3P RANSAC on that view's keypoint depths -> ``T_via_k`` in metres;
* without (an RGB-only robot, or a pass whose unit is not the metre): against every own
  view by its essential matrix. The translation is put in the pass's unit by the points the
  pass triangulated in that view. Where it has none it keeps unit length, counted
  ``cross-unscaled``: its rotation and direction still hold.

A cascade keeps the cost down. The XFeat mutual-NN matches the pass already has come
first. The learned matcher (:class:`LearnedMatcher`) runs only when none of them reaches
``min_inliers``, against the ``max_views`` own views with most mutual-NN matches. A
registration needs ``min_inliers_mnn`` verified inliers from the mutual-NN stage (the
evidence the joint pass asks of a view it places by PnP), or ``min_inliers`` from the
learned one. For the essential matrix it also needs an inlier ratio of
:data:`MIN_INLIER_RATIO`. A learned registration replaces the mutual-NN one of its view
when it has more inliers. Registrations come most inliers first.

The fallback (``fallback``) serves passes where collaborators join the joint reconstruction
(RGB-D). A collaborator the joint pass left unplaced is registered here when the robot asks
(``View.try_hard``: no anchor of its sender yet). Since the joint pass's own evidence already
failed, the rules are stricter than above. Both stages need ``min_inliers_pnp`` inliers, the
learned one tries :data:`FALLBACK_MAX_VIEWS` own views, and every placement, whatever its
inliers, must pass the appearance check. Without these rules the fallback places wrong poses:
half turns on streets whose two sides look alike, or a view that saw nothing the robot saw.

A metric placement of a collaborator on fewer than :data:`APPEARANCE_MAX_INLIERS` inliers, in the
joint pass or here, must also pass the **appearance check** (:func:`check_appearance`). The own
view's depth pixels, moved into the collaborator's camera by the placement, must look like what
the collaborator saw there. The normalised cross-correlation of the grey levels must reach
``appearance_min_ncc``, and that of their texture alone its own threshold (see below). Repeated
or mirrored structure gives a handful of consistent keypoint inliers for a pose that no surface
supports. The collaborator is then put about where the robot stands, turned alike, while it is
metres away or facing elsewhere. Such a placement is dropped (reason
:data:`cerpe.protocols.REASON_APPEARANCE`).

Why also a high pass (:data:`APPEARANCE_HIGHPASS_PX`, ``appearance_min_ncc_highpass``): in plain
grey levels any two upright cameras share the layout (bright sky or ceiling above, dark road or
floor below). So a placement turned half a turn, or moved metres along a street, still
correlates well. Less their blur, only texture and edges count, and the high-passed correlation
ranks right placements above wrong ones better. But a half turn on a street whose two sides
look alike can correlate there while the plain levels disagree, so a placement must pass both.
"""
from __future__ import annotations

import time
from typing import Any, Mapping, Sequence

import numpy as np

from ...geometry import se3_inverse
from ...protocols import REASON_APPEARANCE, Registration
from ..cache import LRUCache
from ..config import CrossConfig
from .context import P3P_SAMPLE, Pass, Recon
from .matching import keypoint_depths, pixels_to_rays, pose_to_T
from .two_view import MIN_SCALE_POINTS, relative_pose, triangulate_pair
from .vote import photometric_agreements

FALLBACK_MAX_VIEWS = 1  # own views the fallback's learned stage tries (ALIKED and LightGlue are costly)
MIN_INLIER_RATIO = 0.2  # an essential-matrix registration needs this fraction of its matches as inliers
PNP_PX = 3.0  # P3P RANSAC threshold of a registration on an own view's depth, px
EPIPOLAR_PX = 1.0  # essential-matrix RANSAC threshold (Sampson error), px
FILTER_THRESHOLD = 0.1  # LightGlue's match confidence threshold
FEATURE_CACHE_SIZE = 32  # ALIKED feature sets kept (LRU by content key)
SCALE_MATCH_PX = 1.5  # a registration inlier takes the depth of a reconstructed keypoint this close, px
# the appearance check (:func:`check_appearance`): placements on at least APPEARANCE_MAX_INLIERS
# inliers are not judged; a judged one needs APPEARANCE_MIN_PIXELS moved pixels inside the
# collaborator's image; the high pass subtracts a blur of APPEARANCE_HIGHPASS_PX (0: not asked)
APPEARANCE_MAX_INLIERS = 40
APPEARANCE_MIN_PIXELS = 200
APPEARANCE_HIGHPASS_PX = 12.0


class LearnedMatcher:
    """LightGlue over ALIKED (``matcher="aliked"``) or XFeat features (``"xfeat"``: LighterGlue).

    ALIKED features are cached by the image's content key (the XFeat features'
    fingerprint), so a keyframe is extracted once; XFeat features are the pass's own.
    ``n_pairs`` / ``n_extracted`` count matched pairs and ALIKED extractions.
    """

    def __init__(self, conf: CrossConfig) -> None:
        from ..lightglue import AlikedExtractor, shared_matcher

        self.kind = conf.matcher
        if self.kind == "aliked":
            self.extractor = AlikedExtractor(max_keypoints=conf.max_keypoints, max_side_px=conf.max_side_px)
            self.lightglue = shared_matcher("aliked", FILTER_THRESHOLD)
        else:
            self.extractor = None
            self.lightglue = shared_matcher("xfeat", FILTER_THRESHOLD, conf.max_keypoints)
        self.cache: LRUCache[dict] = LRUCache(FEATURE_CACHE_SIZE)
        self.n_pairs = 0
        self.n_extracted = 0

    def clear_cache(self) -> None:
        self.cache.clear()

    def features(self, p: Pass, s: int) -> dict[str, Any]:
        """The matcher's feature dict of view ``s`` of pass ``p``."""
        from ..lightglue import xfeat_inputs

        f = p.feats[s]
        if self.extractor is None:
            return xfeat_inputs(f)
        out = self.cache.get(f.fingerprint) if f.fingerprint else None
        if out is None:
            out = self.extractor(p.views[s].image)
            self.n_extracted += 1
            if f.fingerprint:
                self.cache.put(f.fingerprint, out)
        return out

    def match(self, f0: Mapping[str, Any], f1: Mapping[str, Any]) -> np.ndarray:
        """``[M,2] int64`` matches between two feature dicts."""
        self.n_pairs += 1
        return self.lightglue({"image0": f0, "image1": f1})["matches"]


def register_collaborators(p: Pass, rec: Recon | None, own: Sequence[int], collab: Sequence[int],
                           learned: Any, strict: Sequence[int] = ()
                           ) -> tuple[dict[int, list[Registration]], dict[int, str]]:
    """Registrations of each collaborator view (index in ``p``) against the own views ``own``.

    ``rec``: the own views' reconstruction (None: nothing placed but view 0); ``learned``:
    a callable returning the :class:`LearnedMatcher` (built on first use) or None. ``strict``:
    collaborators the joint pass already failed to place (the fallback, ``cross.fallback``): both
    stages need ``min_inliers_pnp`` inliers (``min_inliers`` without depth), the learned one tries
    :data:`FALLBACK_MAX_VIEWS` own views, and every placement is judged by the appearance check.
    Returns ``{k: registrations, most inliers first}`` (only views with at least one)
    and a reason per collaborator without one.
    """
    t0 = time.perf_counter()
    regs: dict[int, list[Registration]] = {}
    why: dict[int, str] = {}
    for k in collab:
        found, reason = _register(p, k, own, rec, learned, k in strict)
        if found:
            regs[k] = found
            p.counts["cross-registered"] += 1
        else:
            why[k] = reason
            p.counts["cross-none"] += 1
    p.timings["cross"] = p.timings.get("cross", 0.0) + time.perf_counter() - t0
    return regs, why


def _register(p: Pass, k: int, own: Sequence[int], rec: Recon | None,
              learned: Any, strict: bool = False) -> tuple[list[Registration], str]:
    c = p.conf.cross
    need = c.min_inliers
    if p.Ks[k] is None:
        return [], "no-intrinsics"
    if p.low_tex[k]:
        return [], "low-texture"
    metric = rec is None or rec.metric
    targets = [s for s in own if metric and p.views[s].depth_m is not None and not p.low_tex[s]]
    mode = "pnp" if targets else "essential"
    if mode == "pnp":
        need = c.min_inliers_pnp
    if not targets:
        targets = [s for s in own if not p.low_tex[s]]
    # the essential matrix asks of the mutual-NN stage what the own image-only pass asks of a pair
    need_mnn = c.min_inliers_mnn if mode == "pnp" else max(c.min_inliers_mnn, p.conf.min_inliers)
    if strict:  # the joint pass failed: the mutual-NN stage must reach what the learned one does
        need_mnn = max(need_mnn, need)
    best: dict[int, tuple[np.ndarray | None, int, int]] = {}
    for s in targets:
        m = p.m(s, k)
        best[s] = _verify(p, mode, s, k, p.feats[s].keypoints[m[:, 0]], p.feats[k].keypoints[m[:, 1]], rec,
                          need_mnn)
        if best[s][1] < need_mnn:
            best[s] = (None, best[s][1], best[s][2])
    if targets and max(n for _, n, _ in best.values()) < need and learned is not None and c.matcher != "none":
        lm = learned()
        n_views = FALLBACK_MAX_VIEWS if strict else c.max_views
        order = sorted(targets, key=lambda s: -len(p.m(s, k)))[:n_views]
        fk = lm.features(p, k)
        p.counts["cross-learned"] += 1
        for s in order:
            fs = lm.features(p, s)
            mm = lm.match(fs, fk)
            p.counts["cross-learned-pairs"] += 1
            res = _verify(p, mode, s, k, np.asarray(fs["keypoints"])[mm[:, 0]], np.asarray(fk["keypoints"])[mm[:, 1]],
                          rec, need)
            if res[1] >= need and res[1] > best[s][1]:
                best[s] = res
    out = [Registration(s, T, n, m) for s, (T, n, m) in best.items() if T is not None]
    placed = bool(out)
    if mode == "pnp":
        out = [r for r in out if not check_appearance(p, r.via, k, r.T_via_cam, r.inliers, judge_all=strict)]
    out.sort(key=lambda r: (-r.inliers, r.via))
    if out:
        return out, ""
    if placed:
        return [], REASON_APPEARANCE
    return [], "few-inliers" if any(m >= need_mnn for _, _, m in best.values()) else "few-matches"


def _verify(p: Pass, mode: str, s: int, k: int, uv_s: np.ndarray, uv_k: np.ndarray,
            rec: Recon | None, need: int) -> tuple[np.ndarray | None, int, int]:
    """``(T_s_k or None, verified inliers, matches)`` of matched pixels of views ``s`` and ``k``
    (None below ``need`` inliers)."""
    import poselib

    n_match = len(uv_s)
    if mode == "essential":
        T_k_s, inl, _ = relative_pose(p.ransac(), uv_s, uv_k, p.cams[s], p.cams[k], need, min_matches=need,
                                      epipolar_px=EPIPOLAR_PX, min_inlier_ratio=MIN_INLIER_RATIO)
        n = int(inl.sum())
        if T_k_s is None:
            return None, n, n_match
        T_k_s = T_k_s.copy()
        T_k_s[:3, 3] *= pass_unit(p, rec, s, k, uv_s[inl], uv_k[inl], T_k_s)
        return se3_inverse(T_k_s), n, n_match
    z = keypoint_depths(uv_s, p.views[s].depth_m, p.feats[s].image_hw)
    ok = z > 0
    if ok.sum() < need:
        return None, 0, n_match
    X = pixels_to_rays(uv_s[ok], p.Ks[s]) * z[ok, None]
    pose, info = poselib.estimate_absolute_pose(uv_k[ok].astype(np.float64), X, p.cams[k],
                                                p.ransac((need, len(X), P3P_SAMPLE), max_reproj_error=PNP_PX), {})
    n = int(np.sum(info["inliers"]))
    T_k_s = pose_to_T(pose.R, pose.t)
    if n < need or not np.all(np.isfinite(T_k_s)):
        return None, n, n_match
    return se3_inverse(T_k_s), n, n_match


def pass_unit(p: Pass, rec: Recon | None, s: int, k: int, uv_s: np.ndarray, uv_k: np.ndarray,
              T_k_s: np.ndarray) -> float:
    """Length, in the pass's unit, of the unit translation ``T_k_s`` (view ``s`` placed in ``rec``).

    The registration's inliers of view ``s`` that lie within :data:`SCALE_MATCH_PX` of a
    keypoint with a point of ``rec`` are triangulated at unit baseline; the median ratio
    of their depths in camera ``s`` gives the unit (as :func:`.two_view.two_view_with_scale`
    does). 1 (counted ``cross-unscaled``) without a reconstruction or too few such points.
    """
    if rec is not None and s in rec.obs and len(uv_s):
        ids, kp = rec.obs[s]
        T_s_f = se3_inverse(rec.T[s])
        z_pt = (rec.X[ids] @ T_s_f[:3, :3].T + T_s_f[:3, 3])[:, 2]
        d2 = np.sum((uv_s[:, None, :] - p.feats[s].keypoints[kp][None, :, :]) ** 2, axis=2)
        near = np.argmin(d2, axis=1)
        close = d2[np.arange(len(uv_s)), near] <= SCALE_MATCH_PX ** 2
        X_unit, keep, _, _ = triangulate_pair(uv_s, uv_k, p.Ks[s], p.Ks[k], T_k_s)
        sel = keep & close & (z_pt[near] > 0)
        if sel.sum() >= MIN_SCALE_POINTS:
            unit = float(np.median(z_pt[near[sel]] / X_unit[sel, 2]))
            if np.isfinite(unit) and unit > 0:
                return unit
    p.counts["cross-unscaled"] += 1
    return 1.0


def check_appearance(p: Pass, a: int, k: int, T_a_k: np.ndarray, inliers: int, judge_all: bool = False) -> str:
    """The appearance check of collaborator ``k`` placed at ``T_a_k`` (metres) in own view ``a``
    on ``inliers`` keypoint inliers: ``""`` (agrees, or not judged) or
    :data:`~cerpe.protocols.REASON_APPEARANCE`.

    A placement on at least :data:`APPEARANCE_MAX_INLIERS` inliers is not judged: the keypoints alone
    support it (and an imprecise but right placement over a wide baseline can look unlike the
    collaborator's image pixel by pixel). Below, view ``a``'s depth-prior pixels (the vote grid)
    are moved into camera ``k`` (:func:`.vote.photometric_agreement`). When at least
    :data:`APPEARANCE_MIN_PIXELS` land inside, the normalised cross-correlation of both images' grey
    levels there must reach ``appearance_min_ncc``. That of the same levels less their blur of
    :data:`APPEARANCE_HIGHPASS_PX` (texture, not layout; 0: not asked) must reach
    ``appearance_min_ncc_highpass``. Not
    judged (``""``) either: the check off, ``a`` without a depth prior, either view blank, too few
    pixels inside. Counted ``cross-appearance-<checked|rejected>``. ``judge_all``: whatever the inliers
    (a fallback placement, :func:`register_collaborators`).
    """
    c = p.conf.cross
    if (not c.appearance_check or (int(inliers) >= APPEARANCE_MAX_INLIERS and not judge_all)
            or p.views[a].depth_m is None or p.low_tex[a] or p.low_tex[k] or p.Ks[k] is None
            or not np.all(np.isfinite(T_a_k))):
        return ""
    hp = float(APPEARANCE_HIGHPASS_PX)
    n, nccs = photometric_agreements(p, a, k, se3_inverse(T_a_k), (0.0, hp) if hp > 0 else (0.0,))
    if n < APPEARANCE_MIN_PIXELS or not np.isfinite(nccs[0]):
        return ""
    p.counts["cross-appearance-checked"] += 1
    agrees = nccs[0] >= c.appearance_min_ncc
    if agrees and hp > 0:  # texture too; NaN (no texture there) passes
        agrees = not nccs[1] < c.appearance_min_ncc_highpass
    if agrees:
        return ""
    p.counts["cross-appearance-rejected"] += 1
    return REASON_APPEARANCE


def check_joint_placements(p: Pass, rec: Any, collab: Sequence[int], reasons: list[str]) -> None:
    """The appearance check of the collaborator views ``collab`` that the joint (metric)
    reconstruction ``rec`` placed, against the current view (0), on the points it observes
    (``rec.obs``; none for a two-view placement scaled by the current view's prior). A view that fails leaves
    ``rec`` (in place) with reason :data:`~cerpe.protocols.REASON_APPEARANCE`. An image-only
    reconstruction (unit not the metre) is not checked."""
    if rec is None or not rec.metric or 0 not in rec.T:
        return
    for k in collab:
        if k in rec.T and check_appearance(p, 0, k, se3_inverse(rec.T[0]) @ rec.T[k],
                                           len(rec.obs[k][0]) if k in rec.obs else 0):
            del rec.T[k]
            rec.obs.pop(k, None)
            reasons[k] = REASON_APPEARANCE


def place_collaborators(regs: Mapping[int, Sequence[Registration]], T: np.ndarray, valid: np.ndarray,
                        support: list[int]) -> None:
    """Each registered collaborator's pose in the pass frame through its best registration whose
    view the pass placed: ``T[k] = T[via] @ T_via_k`` and ``support[k]`` that registration's
    inliers (in place; others stay invalid)."""
    for k, rs in regs.items():
        for r in rs:
            if valid[r.via] and r.via != k:
                T[k] = T[r.via] @ r.T_via_cam
                valid[k] = True
                support[k] = int(r.inliers)
                break
