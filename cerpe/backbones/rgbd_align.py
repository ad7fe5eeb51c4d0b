"""Dense RGB-D alignment: refine a relative pose on every pixel instead of a few hundred keypoints.

A pose from 2D-3D keypoint correspondences is limited by keypoint localisation
(XFeat: about 0.5 px). With a narrow field of view it is also limited by the
near-ambiguity of a small rotation and a sideways translation (0.03 deg of yaw looks
like 2 mm of translation at 4 m). Consecutive frames of a robot with a depth source carry far
more evidence: every pixel of the reference with a metric depth predicts the grey
level and the depth the current frame should see there. This module minimises both
residuals over the rigid motion. It works in the manner of dense visual odometry (Kerl
et al., "Robust odometry estimation for RGB-D cameras", ICRA 2013), with a depth term
as in their DVO-SLAM follow-up:

    r_I(p) = I_cur(pi(T X_p)) - I_ref(p)            grey levels (0-255)
    r_Z(p) = Z_cur(pi(T X_p)) - [T X_p]_z           metres

with ``X_p`` the reference pixel ``p`` back-projected with its depth. It runs Gauss-Newton
on a left perturbation of ``T = T_cur_ref``, with Tukey biweights on residuals normalised
by their robust (MAD) spread. So a moving object or an occlusion is down-weighted
rather than averaged in. It only *refines*: the caller gives a pose that is already
right to well within a pixel (the P3P motion chosen by the vote). The result is
refused (the caller keeps its own) when it moves far from it, when too few pixels
take part, or when it does not lower the robust cost.

Pure numpy + OpenCV (remap, blur, Sobel); no files, no models.
Conventions:

* images ``[H,W]`` or ``[H,W,C]`` (any dtype, grey = mean of the channels);
* depth ``[h,w]`` metres (0 / non-finite = no depth; resized to the image by nearest
  neighbour when its size differs);
* ``K`` ``[3,3]`` pinhole, pixel centres at integer coordinates;
* ``T_cur_ref`` ``[4,4]`` maps reference-camera points into the current camera.
"""

from __future__ import annotations

from dataclasses import dataclass
import numpy as np

from ..errors import CerpeError
from ..geometry import se3_inverse

__all__ = ["RGBDAlignError", "AlignResult", "Level", "grey_image", "rgbd_pyramid", "align_rgbd"]


class RGBDAlignError(CerpeError, ValueError):
    """Bad input to the dense alignment (shapes, intrinsics, a non-finite initial pose)."""


# every stride-th reference pixel (both directions) with a depth takes part on the coarser
# pyramid levels (fewer pixels there: a coarse level only has to bring the pose within the next
# level's basin); the finest level's stride is align_rgbd's argument
COARSE_STRIDE = 4
BLUR_SIGMA = 1.0  # Gaussian blur (px) of the grey images: a wider basin, less aliasing
DEPTH_BLUR_SIGMA = 2.0  # blur (px) of the current depth for its gradient (sensor noise is per pixel)
TUKEY_K = 3.0  # Tukey biweight threshold on MAD-normalised residuals
# reference pixels whose depth changes by more than this fraction of itself to a neighbour sit
# on a depth edge: their warp is ill-defined, they are left out
EDGE_TOL = 0.05
MIN_PIXELS = 500  # fewer reference pixels taking part: refused (few-pixels)
MIN_INLIER_RATIO = 0.3  # refused when fewer than this fraction of the used pixels is within 3 sigma at the end
# refused when the refinement moves the pose by more than this (the input is a pose that is
# right to well within a pixel; a big move is a wrong basin)
MAX_CHANGE_M = 0.05
MAX_CHANGE_DEG = 1.0
CONVERGED_PX = 0.01  # stop the finest level when an update moves the pixels by less than this on average (px)
# stop a coarser level when an update moves its pixels by less than this (its px): it only has to
# bring the pose within the next level's basin
COARSE_CONVERGED_PX = 0.05
# refused when the last update on the finest level still moved them by more than this (px): the
# pose was on its way somewhere else (a start outside the basin)
MAX_FINAL_PX = 0.1


@dataclass
class AlignResult:
    """Outcome of :func:`align_rgbd`.

    ``T_cur_ref``: the refined pose ``[4,4]`` when ``ok``, else the initial one;
    ``reason``: why it was refused (``""`` when ok); ``n_pixels``: pixels used in the
    last iteration; ``inlier_ratio``: their fraction within 3 robust sigmas;
    ``cost0``, ``cost``: mean robust cost before and after (on the same normalisation);
    ``iterations``: Gauss-Newton steps taken (all levels); ``change_m``, ``change_deg``:
    how far the result is from the initial pose.
    """

    T_cur_ref: np.ndarray
    ok: bool
    reason: str = ""
    n_pixels: int = 0
    inlier_ratio: float = 0.0
    cost0: float = float("nan")
    cost: float = float("nan")
    iterations: int = 0
    change_m: float = 0.0
    change_deg: float = 0.0


def grey_image(image: np.ndarray) -> np.ndarray:
    """``[H,W]`` float32 grey level (mean of the channels) of an ``[H,W]`` or ``[H,W,C]`` image."""
    import cv2

    img = np.ascontiguousarray(image, np.float32)
    if img.ndim == 2:
        return img
    if img.ndim != 3 or img.shape[2] < 1:
        raise RGBDAlignError(f"grey_image: expected [H,W] or [H,W,C], got shape {img.shape}")
    if img.shape[2] == 1:
        return np.ascontiguousarray(img[:, :, 0])
    return cv2.transform(img, np.full((1, img.shape[2]), 1.0 / img.shape[2], np.float32))


def _depth_at_image(depth_m: np.ndarray, hw: tuple[int, int], what: str) -> np.ndarray:
    """``[H,W]`` float32 map of ``depth_m`` at the image size ``hw`` (nearest neighbour),
    0 where not finite or not positive; ``what`` names the argument in the error."""
    import cv2

    d = np.asarray(depth_m, np.float32)
    if d.ndim != 2 or d.size == 0:
        raise RGBDAlignError(f"align_rgbd: {what} must be [H,W], got shape {d.shape}")
    d = np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)
    if d.shape != hw:
        d = cv2.resize(d, (hw[1], hw[0]), interpolation=cv2.INTER_NEAREST)
    return d


def _sample(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``img`` at float pixel positions (``[N]`` each)."""
    import cv2

    return cv2.remap(img, u.astype(np.float32)[None], v.astype(np.float32)[None], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)[0]


def _robust_sigma(r: np.ndarray, floor: float) -> float:
    return max(1.4826 * float(np.median(np.abs(r - np.median(r)))), floor)


def _robust_w(x: np.ndarray, k: float) -> np.ndarray:
    """IRLS weights of :func:`_robust_cost`."""
    return np.maximum(1.0 - (x / k) ** 2, 0.0) ** 2


def _robust_cost(x: np.ndarray, k: float) -> np.ndarray:
    """Tukey's biweight: a residual beyond ``k`` sigmas costs the same as any other.

    So a moving object that covers a third of the image adds a constant instead of
    pulling the pose its way (Huber's linear tail still lets it pull)."""
    a = np.minimum((x / k) ** 2, 1.0)
    return (k * k / 6.0) * (1.0 - (1.0 - a) ** 3)


@dataclass(frozen=True)
class Level:
    """One image's pyramid level: ``grey`` ``[h,w]`` float32, the same blurred with :data:`BLUR_SIGMA`
    (``blurred``), ``depth_m`` ``[h,w]`` float32 (0: unknown; None without depth) and ``K`` ``[3,3]``."""

    grey: np.ndarray
    blurred: np.ndarray
    depth_m: np.ndarray | None
    K: np.ndarray


def rgbd_pyramid(image: np.ndarray, depth_m: np.ndarray | None, K: np.ndarray, levels: int,
                 what: str = "depth") -> list[Level]:
    """``levels`` :class:`Level` of one image (finest first), read-only. A level down halves the image by
    ``pyrDown``, takes every other depth pixel (averaging would blend across depth edges) and moves
    the intrinsics for pixel centres at integers. It depends on the one image alone, so a caller may
    keep it: a frame is the current view of one alignment and the reference of the next."""
    import cv2

    def level(g: np.ndarray, D: np.ndarray | None, K: np.ndarray) -> Level:
        b = cv2.GaussianBlur(g, (0, 0), BLUR_SIGMA) if BLUR_SIGMA > 0 else g
        for a in (g, b, D, K):
            if a is not None:
                a.setflags(write=False)
        return Level(g, b, D, K)

    K = np.array(K, np.float64)
    g = grey_image(image)
    D = None if depth_m is None else _depth_at_image(depth_m, g.shape, what)
    out = [level(g, D, K)]
    for _ in range(max(int(levels), 1) - 1):
        K = K.copy()
        K[0, 0] /= 2
        K[1, 1] /= 2
        K[0, 2] = (K[0, 2] + 0.5) / 2 - 0.5
        K[1, 2] = (K[1, 2] + 0.5) / 2 - 0.5
        g = cv2.pyrDown(g)
        # pyrDown rounds sizes up like the slicing; keep the depth at the image size
        D = None if D is None else _depth_at_image(np.ascontiguousarray(D[::2, ::2]), g.shape, what)
        out.append(level(g, D, K))
    return out


class _Level:
    """One pyramid level: the reference points and the current view's sampled maps."""

    def __init__(self, ref: Level, cur: Level, use_depth: bool, stride: int) -> None:
        import cv2

        g_ref, D_ref, Kr = ref.blurred, ref.depth_m, ref.K
        g_cur, D_cur, Kc = cur.blurred, cur.depth_m if use_depth else None, cur.K
        H, W = g_ref.shape
        self.Hc, self.Wc = g_cur.shape
        # reference points: every stride-th pixel with a depth, off depth edges
        st = max(int(stride), 1)
        vv, uu = np.mgrid[st // 2:H - 1:st, st // 2:W - 1:st]
        vv, uu = vv.ravel(), uu.ravel()
        z = D_ref[vv, uu]
        zr = D_ref[vv, np.minimum(uu + 1, W - 1)]
        zd = D_ref[np.minimum(vv + 1, H - 1), uu]
        with np.errstate(divide="ignore", invalid="ignore"):
            smooth = (np.abs(zr - z) <= EDGE_TOL * z) & (np.abs(zd - z) <= EDGE_TOL * z)
        keep = (z > 0) & smooth
        uu, vv, z = uu[keep], vv[keep], z[keep].astype(np.float64)
        self.n = len(z)
        self.X_ref = np.column_stack([(uu - Kr[0, 2]) / Kr[0, 0] * z, (vv - Kr[1, 2]) / Kr[1, 1] * z, z])
        self.I_ref = g_ref[vv, uu].astype(np.float64)
        self.g_cur = g_cur
        self.gx = cv2.Sobel(g_cur, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / 8)
        self.gy = cv2.Sobel(g_cur, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / 8)
        self.use_depth = D_cur is not None
        if self.use_depth:
            # the residual reads the raw depth (a blurred one is biased at creases, where a
            # wall meets the floor); only the gradient, i.e. the Jacobian, reads a smoothed one
            m = (D_cur > 0).astype(np.float32)
            self.D_raw = D_cur
            ds = DEPTH_BLUR_SIGMA
            if ds > 0:  # normalised convolution: holes do not drag the depth towards 0
                num = cv2.GaussianBlur(D_cur * m, (0, 0), ds)
                den = cv2.GaussianBlur(m, (0, 0), ds)
                has = den > 0.5
                D_s = np.where(has, num / np.maximum(den, 1e-6), 0.0).astype(np.float32)
            else:
                has, D_s = D_cur > 0, D_cur
            # a gradient across the border of a region without depth is a jump to 0, not a slope
            self.valid_cur = m * cv2.erode(has.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(np.float32)
            self.dx = cv2.Sobel(D_s, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / 8)
            self.dy = cv2.Sobel(D_s, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / 8)
        self.fx, self.fy, self.cx, self.cy = Kc[0, 0], Kc[1, 1], Kc[0, 2], Kc[1, 2]

    def residuals(self, R: np.ndarray, t: np.ndarray, with_jac: bool):
        """``(idx, rI, rZ, JI, JZ, zc)`` of the points that land inside the current image."""
        fx, fy, cx, cy = self.fx, self.fy, self.cx, self.cy
        Xc = self.X_ref @ R.T + t
        x, y, zc = Xc[:, 0], Xc[:, 1], Xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            iz = 1.0 / zc
            u, v = fx * x * iz + cx, fy * y * iz + cy
        ok = (zc > 1e-6) & (u >= 1) & (u <= self.Wc - 2) & (v >= 1) & (v <= self.Hc - 2)
        idx = np.flatnonzero(ok)
        u, v = u[idx], v[idx]
        rI = _sample(self.g_cur, u, v).astype(np.float64) - self.I_ref[idx]
        rZ = None
        if self.use_depth:
            vz = _sample(self.valid_cur, u, v) > 0.999
            rZ = np.where(vz, _sample(self.D_raw, u, v).astype(np.float64) - zc[idx], np.nan)
        if not with_jac:
            return idx, rI, rZ, None, None, zc[idx], None
        x, y, iz = x[idx], y[idx], iz[idx]
        xz, yz = x * iz, y * iz
        zero = np.zeros_like(iz)
        du = np.column_stack([fx * iz, zero, -fx * xz * iz, -fx * xz * yz, fx * (1 + xz * xz), -fx * yz])
        dv = np.column_stack([zero, fy * iz, -fy * yz * iz, -fy * (1 + yz * yz), fy * xz * yz, fy * xz])
        JI = _sample(self.gx, u, v).astype(np.float64)[:, None] * du + _sample(self.gy, u, v).astype(np.float64)[:, None] * dv
        JZ = None
        if self.use_depth:
            dz = np.column_stack([zero, zero, np.ones_like(iz), y, -x, zero])
            JZ = (_sample(self.dx, u, v).astype(np.float64)[:, None] * du
                  + _sample(self.dy, u, v).astype(np.float64)[:, None] * dv - dz)
        return idx, rI, rZ, JI, JZ, zc[idx], (du, dv)

    @staticmethod
    def scales(r: tuple) -> tuple[float, float]:
        """Robust spreads of the grey residual and of the depth residual over ``z^2``."""
        _, rI, rZ, _, _, zc, _ = r
        sZ = 1e-3
        if rZ is not None and np.isfinite(rZ).sum() >= 10:
            okz = np.isfinite(rZ)
            sZ = _robust_sigma(rZ[okz] / zc[okz] ** 2, 1e-4)
        return _robust_sigma(rI, 0.5), sZ

    @staticmethod
    def cost(r: tuple, sc: tuple[float, float], k: float) -> float:
        """Mean robust cost of the normalised residuals."""
        _, rI, rZ, _, _, zc, _ = r
        total = float(np.sum(_robust_cost(rI / sc[0], k)))
        n = len(rI)
        if rZ is not None:
            okz = np.isfinite(rZ)
            total += float(np.sum(_robust_cost(rZ[okz] / (sc[1] * zc[okz] ** 2), k)))
            n += int(okz.sum())
        return total / max(n, 1)

    def step(self, R: np.ndarray, t: np.ndarray, sc: tuple[float, float] | None, k: float, min_pixels: int):
        """One Gauss-Newton step: ``(R, t, scales, px)`` with ``px`` the mean image motion (px)
        of the step, or None (too few pixels, singular)."""
        from ..geometry import so3_exp

        r = self.residuals(R, t, True)
        idx, rI, rZ, JI, JZ, zc, (du, dv) = r
        if len(idx) < max(min_pixels, 6):
            return None
        if sc is None:
            sc = self.scales(r)
        wI = _robust_w(rI / sc[0], k) / sc[0] ** 2
        Hm = (JI * wI[:, None]).T @ JI
        b = (JI * wI[:, None]).T @ rI
        if rZ is not None:
            okz = np.isfinite(rZ)
            s_z = sc[1] * zc[okz] ** 2
            wZ = _robust_w(rZ[okz] / s_z, k) / s_z ** 2
            Jz = JZ[okz]
            Hm += (Jz * wZ[:, None]).T @ Jz
            b += (Jz * wZ[:, None]).T @ rZ[okz]
        try:
            delta = -np.linalg.solve(Hm, b)
        except np.linalg.LinAlgError:
            return None
        if not np.all(np.isfinite(delta)):
            return None
        dR = so3_exp(delta[3:])
        px = float(np.mean(np.hypot(du @ delta, dv @ delta)))
        return dR @ R, dR @ t + delta[:3], sc, px


def align_rgbd(image_ref: np.ndarray, depth_ref_m: np.ndarray, image_cur: np.ndarray,
               depth_cur_m: np.ndarray | None, K_ref: np.ndarray, K_cur: np.ndarray,
               T_cur_ref: np.ndarray, stride: int = 8, iterations: int = 6, levels: int = 3,
               use_depth: bool = True, pyramids: tuple[list[Level], list[Level]] | None = None) -> AlignResult:
    """Refine ``T_cur_ref`` by dense photometric (+ depth) alignment; see the module docstring.

    Args:
        image_ref, image_cur: ``[H,W]`` / ``[H,W,C]`` images (grey = channel mean).
        depth_ref_m: ``[h,w]`` metric depth of the reference (required: it gives the 3D points).
        depth_cur_m: ``[h,w]`` metric depth of the current view, or None (photometric only).
        K_ref, K_cur: ``[3,3]`` intrinsics at the images' resolutions.
        T_cur_ref: ``[4,4]`` initial pose (reference-camera points into the current camera).
        stride: every stride-th reference pixel (both directions) with a depth takes part on the
            finest level (:data:`COARSE_STRIDE` on the others).
        iterations: Gauss-Newton steps per pyramid level.
        levels: pyramid levels (1: full resolution only); each coarser level halves the image and
            doubles the basin, for an initial pose a few pixels off.
        use_depth: weight the depth residual at all (False: photometric only).
        pyramids: ``(reference, current)`` :func:`rgbd_pyramid` of these images (the current one's
            with its depth when ``use_depth``), at least ``levels`` deep, when the caller keeps them;
            None: built here.

    Returns:
        :class:`AlignResult`; never raises for a pose it cannot refine (``ok`` False and a
        reason), only for malformed input.
    """
    T0 = np.asarray(T_cur_ref, np.float64)
    if T0.shape != (4, 4) or not np.all(np.isfinite(T0)):
        raise RGBDAlignError(f"align_rgbd: T_cur_ref must be a finite [4,4], got {T0.shape}")
    Kr, Kc = np.asarray(K_ref, np.float64), np.asarray(K_cur, np.float64)
    if Kr.shape != (3, 3) or Kc.shape != (3, 3) or not (np.all(np.isfinite(Kr)) and np.all(np.isfinite(Kc))):
        raise RGBDAlignError("align_rgbd: K_ref and K_cur must be finite [3,3]")
    use_depth = bool(use_depth) and depth_cur_m is not None
    n_levels = max(int(levels), 1)
    if pyramids is None:
        pyramids = (rgbd_pyramid(image_ref, depth_ref_m, Kr, n_levels, "reference depth"),
                    rgbd_pyramid(image_cur, depth_cur_m if use_depth else None, Kc, n_levels, "current depth"))
    ref, cur = pyramids
    if len(ref) < n_levels or len(cur) < n_levels or ref[0].depth_m is None or (use_depth and cur[0].depth_m is None):
        raise RGBDAlignError(f"align_rgbd: pyramids must be {n_levels} levels deep, with depth")
    result = AlignResult(T_cur_ref=T0.copy(), ok=False)
    k = TUKEY_K
    fine = _Level(ref[0], cur[0], use_depth, stride=int(stride))
    if fine.n < MIN_PIXELS:
        result.reason = "few-pixels"
        return result
    # noise levels and starting cost on the finest level at the initial pose: the final
    # cost is measured on the same normalisation, so the two compare
    r0 = fine.residuals(T0[:3, :3], T0[:3, 3], False)
    if len(r0[0]) < MIN_PIXELS:
        result.reason = "few-pixels"
        return result
    fine_scales = fine.scales(r0)
    result.cost0 = fine.cost(r0, fine_scales, k)
    R, t = T0[:3, :3].copy(), T0[:3, 3].copy()
    last_px = float("inf")
    for lev in range(n_levels - 1, -1, -1):
        L = fine if lev == 0 else _Level(ref[lev], cur[lev], use_depth, stride=COARSE_STRIDE)
        if L.n < MIN_PIXELS // (4 ** lev):
            continue
        sc = fine_scales if lev == 0 else None
        for _ in range(int(iterations)):
            out = L.step(R, t, sc, k, MIN_PIXELS // (4 ** lev))
            if out is None:
                result.reason = "degenerate" if lev == 0 else "few-pixels"
                if lev == 0:
                    return result
                break
            R, t, sc, last_px = out
            result.iterations += 1
            if last_px < (CONVERGED_PX if lev == 0 else COARSE_CONVERGED_PX):
                break

    rr = fine.residuals(R, t, False)
    idx, rI = rr[0], rr[1]
    result.n_pixels = int(len(idx))
    if len(idx) < MIN_PIXELS:
        result.reason = "few-pixels"
        return result
    result.cost = fine.cost(rr, fine_scales, k)
    result.inlier_ratio = float(np.mean(np.abs(rI / fine_scales[0]) <= 3.0))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    D = T @ se3_inverse(T0)
    result.change_m = float(np.linalg.norm(D[:3, 3]))
    result.change_deg = float(np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1))))
    if not np.all(np.isfinite(T)):
        result.reason = "degenerate"
    elif result.change_m > MAX_CHANGE_M or result.change_deg > MAX_CHANGE_DEG:
        result.reason = "moved-too-far"
    elif last_px > MAX_FINAL_PX:
        result.reason = "not-converged"
    elif result.inlier_ratio < MIN_INLIER_RATIO:
        result.reason = "few-inliers"
    elif not result.cost < result.cost0:
        result.reason = "no-improvement"
    else:
        result.ok = True
        result.T_cur_ref = T
    return result
