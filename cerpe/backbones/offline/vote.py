"""The motion vote: which rigid motion of the current view the static scene supports.

RANSAC on keypoints can be won by whatever holds most keypoints: a textured object
that moves, or a facade of repeated windows matched one period off. The vote counts
surfaces instead. Every :data:`VOTE_STRIDE`-th pixel of the depth-prior view is moved by
each candidate motion into the current view. It counts for the motions under which it
lands on a consistent depth *and* grey level. Depth alone cannot tell forward motion
over a flat floor from standing still; grey level alone cannot tell motions apart
over blank walls. An older keyframe reached through the memo's motion chain votes
too (:data:`VOTE_VIEWS`): an object that moved with the camera agrees with a wrong motion
in the newest frame only. Pixels a view's own motion did not explain (its memo's ``moving`` mask)
do not vote.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from .context import VOTE_CHAIN_HOPS, Pass
from .matching import map_index, pixels_to_rays

VOTE_STRIDE = 4  # every VOTE_STRIDE-th pixel (both directions) of a view's depth prior votes
VOTE_DEPTH_TOL = 0.05  # a moved pixel's depth agrees within this fraction of the other prior's
VOTE_GREY_TOL = 6.0  # ... and its grey level within this (0-255), both images blurred with VOTE_BLUR_SIGMA px
VOTE_BLUR_SIGMA = 1.0
# one depth scale per motion and frame pair, for a prior whose scale wanders per frame. It is fitted
# on the pixels whose depths agree within a factor 1 + VOTE_DEPTH_SCALE_SEARCH, and bounded to a
# factor 1 + VOTE_DEPTH_SCALE_MAX (about a monocular prior's per-frame scale noise; 0: off)
VOTE_DEPTH_SCALE_MAX = 0.08
VOTE_DEPTH_SCALE_SEARCH = 0.15
# the moving mask's depth tolerance widens to VOTE_MOVING_SPREAD_K robust sigmas of the chosen
# motion's depth residuals, at most VOTE_DEPTH_TOL_MAX (0: off)
VOTE_MOVING_SPREAD_K = 3.0
VOTE_DEPTH_TOL_MAX = 0.2
VOTE_VIEWS = 1  # older views (reached through the memos' motion chains) that vote too


def consistency(p: Pass, a: int, b: int, T_b_a: Sequence[np.ndarray],
                exclude: np.ndarray | None = None, spread_k: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``(inside, consistent)``, both ``[len(T_b_a), n_grid]`` bool: view ``a``'s prior depth
    pixels on the :data:`VOTE_STRIDE` grid, moved into view ``b`` by each ``T_b_a[h]``.

    ``inside``: in front of ``b`` and within its image; ``consistent``: also ``b``'s prior
    depth there within :data:`VOTE_DEPTH_TOL` (relative) of the moved depth times the motion's
    depth scale (:func:`depth_scale`) and its grey level (both images blurred with
    :data:`VOTE_BLUR_SIGMA`) within :data:`VOTE_GREY_TOL`. Grid pixels without a prior depth, or
    set in ``exclude`` (``[n_grid]`` bool), are neither. ``spread_k`` > 0 widens the depth
    tolerance of each motion to ``spread_k`` robust sigmas of its log depth residuals
    (:func:`depth_scale`), at most :data:`VOTE_DEPTH_TOL_MAX`. That is for one motion already
    chosen (the moving mask), never between motions (a wrong one would widen its own)."""
    Db = np.asarray(p.views[b].depth_m)
    grey = blurred_greys(p, (a, b), VOTE_BLUR_SIGMA)
    Hb, Wb = p.feats[b].image_hw
    hb, wb = Db.shape
    D_flat = np.ascontiguousarray(Db).reshape(-1)
    vv, uu, ok, X = grid_points(p, a, exclude)
    sel = np.flatnonzero(ok)
    g_a = grey[0][vv[sel], uu[sel]]
    inside = np.zeros((len(T_b_a), len(ok)), bool)
    consistent = np.zeros((len(T_b_a), len(ok)), bool)
    for h, T in enumerate(T_b_a):
        Xb, ub, vb, ins = project_points(p, b, X, T)
        inside[h, sel] = ins
        ub, vb, zi, gi = ub[ins], vb[ins], Xb[ins, 2], g_a[ins]
        meas = D_flat[map_index(vb, hb, Hb) * wb + map_index(ub, wb, Wb)].astype(np.float64)
        g = bilinear(grey[1], ub, vb)
        grey_ok = np.abs(g - gi) <= VOTE_GREY_TOL
        s, spread = depth_scale(zi, meas, grey_ok, VOTE_DEPTH_TOL, VOTE_DEPTH_SCALE_MAX, VOTE_DEPTH_SCALE_SEARCH)
        tol = VOTE_DEPTH_TOL
        if spread_k > 0:
            tol = max(tol, min(spread_k * spread, VOTE_DEPTH_TOL_MAX))
        with np.errstate(divide="ignore", invalid="ignore"):
            depth_ok = np.isfinite(meas) & (meas > 0) & (np.abs(s * zi - meas) <= tol * meas)
        consistent[h, sel[ins]] = depth_ok & grey_ok
    return inside, consistent


def depth_scale(z_pred: np.ndarray, z_meas: np.ndarray, grey_ok: np.ndarray, tol: float,
                scale_max: float, search: float | None = None) -> tuple[float, float]:
    """One depth scale ``s`` of a motion, and the robust sigma of the log ratios about it.

    ``s * z_pred`` (``[n]``, depths moved by the motion) best matches ``z_meas`` (``[n]``, the
    other view's prior there). ``s`` is the median ratio over the pixels whose grey level
    agrees (``grey_ok``) and whose depths agree within ``(1 + search) * (1 + tol)`` (``search``
    defaults to ``scale_max``). It is clipped to a factor ``1 + scale_max`` either way, and is 1
    with fewer than 3 such pixels or ``scale_max`` <= 0 (off). The robust sigma (1.4826 MAD)
    over those pixels (0 without any) is what is left of the prior's error within a frame (a
    network's smooth distortion) once the scale is fitted. The bound is about the prior's own
    per-frame scale noise. A wider one lets a motion fit away part of a real depth change
    (moving forward towards a scene looks much like a scale).

    Why: a depth prior whose metric scale wanders from frame to frame (a monocular depth
    network) fails a tight relative depth test over the whole static scene, which then
    counts as moving. The scale is one number per motion and frame pair, so an object
    moving in the scene still disagrees with the static part it is fitted on."""
    smax = np.log1p(max(scale_max, 0.0))
    window = np.log1p(max(scale_max if search is None else search, 0.0)) + np.log1p(tol)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.log(z_meas / z_pred)
    use = grey_ok & np.isfinite(r) & (np.abs(r) <= window)
    if use.sum() < 3:
        return 1.0, 0.0
    m = float(np.clip(np.median(r[use]), -smax, smax))
    return float(np.exp(m)), float(1.4826 * np.median(np.abs(r[use] - m)))


def motion_votes(p: Pass, d: int, T_0_d: Sequence[np.ndarray]) -> np.ndarray:
    """``[len(T_0_d)]`` counts of view ``d``'s grid pixels consistent under each motion
    ``T_0_d[h]`` (camera-``d`` points into the current camera). Only pixels that every
    motion keeps in view vote (the floor just below a camera moving forward leaves the
    image and would otherwise count for standing still only); ``d``'s moving pixels do not."""
    if not T_0_d:
        return np.zeros(0, np.int64)
    inside, consistent = consistency(p, d, 0, T_0_d, exclude=p.moving(d))
    return np.count_nonzero(consistent & inside.all(axis=0), axis=1).astype(np.int64)


def chained_views(p: Pass, d: int) -> list[tuple[int, np.ndarray]]:
    """Other views of the pass with a depth prior whose pose relative to view ``d`` the
    motion chain of ``d``'s memo gives: ``[(k, T_d_k)]``, at most :data:`VOTE_VIEWS`, reached
    within :data:`~.context.VOTE_CHAIN_HOPS` hops."""
    want = VOTE_VIEWS
    if want <= 0:
        return []
    index = {p.views[k].key: k for k in range(1, len(p.views))
             if k != d and p.views[k].depth_m is not None and not p.low_tex[k]}
    out: list[tuple[int, np.ndarray]] = []
    T_d_key = np.eye(4)
    for key, T_key_anchor in p.chain(d)[:VOTE_CHAIN_HOPS]:
        T_d_key = T_d_key @ T_key_anchor
        if key in index:
            out.append((index[key], T_d_key.copy()))
            if len(out) >= want:
                break
    return out


def choose_motion(p: Pass, d: int, T_0_d: Sequence[np.ndarray]) -> int:
    """Index of the motion (camera-``d`` points into the current camera) with the most votes
    of view ``d`` and of the views its chain reaches."""
    return int(np.argmax(total_votes(p, d, T_0_d)))


def total_votes(p: Pass, d: int, T_0_d: Sequence[np.ndarray]) -> np.ndarray:
    """``[len(T_0_d)]`` votes of view ``d`` and of the views its chain reaches for each motion."""
    votes = motion_votes(p, d, T_0_d)
    for k, T_d_k in chained_views(p, d):
        votes = votes + motion_votes(p, k, [T @ T_d_k for T in T_0_d])
    return votes


def moving_pixels(p: Pass, d: int, T_d_0: np.ndarray) -> np.ndarray | None:
    """``[n_grid] bool``: the current view's grid pixels that the chosen motion ``T_d_0``
    (current-camera points into camera ``d``) does not explain against view ``d`` (a moving
    object, mostly); None when ``mask_moving`` is off or the current view has no prior.
    The depth tolerance widens with the motion's own depth residuals (:data:`VOTE_MOVING_SPREAD_K`)."""
    if not p.conf.mask_moving or p.views[0].depth_m is None:
        return None
    inside, consistent = consistency(p, 0, d, [T_d_0], spread_k=VOTE_MOVING_SPREAD_K)
    return inside[0] & ~consistent[0]


def photometric_agreement(p: Pass, a: int, b: int, T_b_a: np.ndarray,
                          blur_px: float | None = None, highpass_px: float = 0.0) -> tuple[int, float]:
    """How well view ``b``'s image agrees with view ``a``'s, moved by ``T_b_a`` (camera-``a``
    points into camera ``b``) on ``a``'s depth prior: ``(n, ncc)``.

    ``n`` counts the grid pixels of ``a`` that land inside ``b``. ``ncc`` is the normalised
    cross-correlation of both blurred grey levels there (gain and offset of either camera do
    not matter). ``(n, nan)`` below 2 such pixels. ``blur_px``: the Gaussian blur of both
    images (default :data:`VOTE_BLUR_SIGMA`); a wider one forgives the few pixels a right but
    imprecise placement is off by. ``highpass_px`` > 0: both images less their Gaussian blur of
    that sigma first. Then only texture and edges count, not the layout (bright sky above,
    dark ground below) that any two cameras held alike share.

    Keypoint inliers say only that some features agree; a placement from repeated or
    mirrored structure agrees there and nowhere else, while a true one makes the whole
    shared surface look alike."""
    n, (ncc,) = photometric_agreements(p, a, b, T_b_a, (highpass_px,), blur_px)
    return n, ncc


def photometric_agreements(p: Pass, a: int, b: int, T_b_a: np.ndarray, highpass_px: Sequence[float],
                           blur_px: float | None = None) -> tuple[int, list[float]]:
    """:func:`photometric_agreement` for each of ``highpass_px`` (0: none) over one projection of
    ``a``'s grid: ``(n, [ncc per highpass])``."""
    vv, uu, ok, X = grid_points(p, a)
    _, ub, vb, ins = project_points(p, b, X, T_b_a)
    n = int(ins.sum())
    if n < 2:
        return n, [float("nan")] * len(highpass_px)
    grey = blurred_greys(p, (a, b), float(VOTE_BLUR_SIGMA if blur_px is None else blur_px))
    out = []
    for hp in highpass_px:
        g0, g1 = grey
        if hp > 0:
            low = blurred_greys(p, (a, b), float(hp))
            g0, g1 = g0 - low[0], g1 - low[1]
        g_a = g0[vv[ok][ins], uu[ok][ins]].astype(np.float64)
        g = bilinear(g1, ub[ins], vb[ins]).astype(np.float64)
        da, db = g_a - g_a.mean(), g - g.mean()
        den = float(np.sqrt((da @ da) * (db @ db)))
        out.append(float(da @ db / den) if den > 0 else float("nan"))
    return n, out


def blurred_greys(p: Pass, views: Sequence[int], sigma: float) -> list[np.ndarray]:
    """Grey images of ``views``, blurred with ``sigma`` px (none at 0); read-only (:meth:`Pass.grey`)."""
    return [p.grey(k, sigma) for k in views]


def grid_points(p: Pass, a: int, exclude: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """View ``a``'s :data:`VOTE_STRIDE` grid: rows ``vv``, columns ``uu`` ``[n_grid]``, the mask ``ok`` of
    grid pixels with a prior depth (and not in ``exclude``), their points ``X [ok.sum(),3]`` in camera ``a``.
    Read-only arrays; the grid of a prior is cached (:meth:`Pass.derived`): a frame votes again as
    the previous frame and as an older keyframe."""
    depth, K, hw = p.views[a].depth_m, p.Ks[a], p.feats[a].image_hw
    vv, uu, ok, X = p.derived(("vote-grid", VOTE_STRIDE, *p.prior_key(a)), lambda: _grid(depth, K, hw))
    if exclude is not None and exclude.shape == ok.shape:
        X = X[~exclude[ok]]
        ok = ok & ~exclude
    return vv, uu, ok, X


def _grid(depth_m: np.ndarray, K: np.ndarray, image_hw: tuple[int, int]
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`grid_points` of a depth prior ``[h,w]`` of an image ``image_hw`` with intrinsics ``K``, read-only."""
    Da = np.asarray(depth_m, np.float64)
    st = max(VOTE_STRIDE, 1)
    H, W = image_hw
    vv, uu = np.mgrid[st // 2:H:st, st // 2:W:st]
    vv, uu = vv.ravel(), uu.ravel()
    z = Da[map_index(vv.astype(np.float64), Da.shape[0], H), map_index(uu.astype(np.float64), Da.shape[1], W)]
    ok = np.isfinite(z) & (z > 0)
    uv = np.column_stack([uu[ok], vv[ok]]).astype(np.float64)
    out = (vv, uu, ok, pixels_to_rays(uv, K) * z[ok, None])
    for arr in out:
        arr.setflags(write=False)
    return out


def project_points(p: Pass, b: int, X: np.ndarray, T_b_a: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points ``X`` moved by ``T_b_a`` into camera ``b``: ``(Xb, u, v, inside)`` (in front, within the image)."""
    Hb, Wb = p.feats[b].image_hw
    Xb = X @ T_b_a[:3, :3].T + T_b_a[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        pr = Xb @ p.Ks[b].T
        ub, vb = pr[:, 0] / pr[:, 2], pr[:, 1] / pr[:, 2]
    ins = (Xb[:, 2] > 0) & (ub >= 0) & (ub <= Wb - 1) & (vb >= 0) & (vb <= Hb - 1)
    return Xb, ub, vb, ins


def bilinear(g: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Image ``g`` sampled bilinearly at pixels ``(u, v)`` inside it."""
    h, w = g.shape[:2]
    x0, y0 = np.minimum(u.astype(np.int64), w - 2), np.minimum(v.astype(np.int64), h - 2)
    ax, ay = u - x0, v - y0
    i = y0 * w + x0  # flat indices: one gather each, cheaper than a pair of index arrays
    gf = np.ascontiguousarray(g).reshape(h * w, *g.shape[2:])
    return ((1 - ax) * (1 - ay) * gf[i] + ax * (1 - ay) * gf[i + 1]
            + (1 - ax) * ay * gf[i + w] + ax * ay * gf[i + w + 1])
