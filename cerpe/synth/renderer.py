"""A small CPU renderer: textured rectangles and boxes -> RGB and exact metric depth.

Geometry is a set of planar rectangles (:class:`FaceSet`); a box is six of them.
Each face has an origin, two orthonormal in-plane axes ``eu, ev`` (``eu x ev`` is
the outward normal: faces are one-sided and back faces are culled, so a camera
inside a closed box sees through it), extents in metres and a material.

Rendering is a z-buffer over exact ray-plane intersections: per face, the pixels
of its projected bounding box (after near-plane clipping) are intersected with
the face's plane analytically, vectorised over those pixels; the nearest hit
wins. Rays are ``K^-1 [u, v, 1]`` (OpenCV axes, pixel centres at integer
coordinates) with unit z, so the ray parameter *is* the z-depth along the optical
axis, in metres. Pixels that hit nothing show a sky gradient (outdoor) and have
depth 0, which everywhere in ``cerpe`` means "no surface / unknown".

There is no supersampling: it quadruples the cost and would break the 5-minute
budget of the paper-default suite. Textures are instead footprint-filtered in
:mod:`cerpe.synth.noise`, and texture edges are anti-aliased analytically.
Object silhouettes remain aliased at one pixel.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..scene import CameraIntrinsics
from . import textures as tx
from .errors import SynthError
from .noise import PerFace, fbm, mix
from .shaders import SHADERS


@dataclass(frozen=True)
class Material:
    """``kind`` (a :mod:`textures` kind), base ``color`` RGB in [0,1], ``prm`` (4 floats), ``seed``."""

    kind: int
    color: tuple[float, float, float] = (0.6, 0.6, 0.6)
    prm: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    seed: int = 0


@dataclass
class FaceSet:
    """``F`` one-sided textured rectangles, as parallel arrays.

    Attributes:
        origin: ``[F,3]`` world position of the face's (u=0, v=0) corner.
        eu, ev: ``[F,3]`` orthonormal in-plane axes; normal = ``eu x ev``.
        size: ``[F,2]`` extents (lu, lv) in metres along eu and ev.
        kind: ``[F]`` material kind; seed ``[F]``; color ``[F,3]``; prm ``[F,4]``.
    """

    origin: np.ndarray
    eu: np.ndarray
    ev: np.ndarray
    size: np.ndarray
    kind: np.ndarray
    seed: np.ndarray
    color: np.ndarray
    prm: np.ndarray

    def __len__(self) -> int:
        return len(self.kind)

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.eu, self.ev)

    @staticmethod
    def empty() -> "FaceSet":
        z3 = np.zeros((0, 3))
        return FaceSet(z3, z3, z3, np.zeros((0, 2)), np.zeros(0, np.int32), np.zeros(0, np.int64),
                       z3, np.zeros((0, 4)))

    @staticmethod
    def concat(sets: list["FaceSet"]) -> "FaceSet":
        sets = [s for s in sets if len(s)]
        if not sets:
            return FaceSet.empty()
        return FaceSet(*[np.concatenate([getattr(s, k) for s in sets]) for k in
                         ("origin", "eu", "ev", "size", "kind", "seed", "color", "prm")])

    def transformed(self, T_world_obj: np.ndarray) -> "FaceSet":
        """Faces given in an object frame, moved into the world by ``T_world_obj``."""
        R, t = T_world_obj[:3, :3], T_world_obj[:3, 3]
        return FaceSet(self.origin @ R.T + t, self.eu @ R.T, self.ev @ R.T, self.size, self.kind, self.seed,
                       self.color, self.prm)


def quad(origin, u_vec, v_vec, mat: Material) -> FaceSet:
    """One rectangle spanned by ``u_vec`` and ``v_vec`` (need not be unit; must be orthogonal)."""
    o, a, b = (np.asarray(x, float) for x in (origin, u_vec, v_vec))
    la, lb = np.linalg.norm(a), np.linalg.norm(b)
    if la <= 0 or lb <= 0 or abs(a @ b) > 1e-6 * la * lb:
        raise SynthError(f"quad: edges must be non-zero and orthogonal, got {a} and {b}")
    return FaceSet(o[None], (a / la)[None], (b / lb)[None], np.array([[la, lb]]), np.array([mat.kind], np.int32),
                   np.array([mat.seed], np.int64), np.array([mat.color], float), np.array([mat.prm], float))


def box(center_xy, z0: float, size, yaw: float, side: Material, top: Material | None = None,
        front: Material | None = None, back: Material | None = None, bottom: bool = False,
        sides: tuple[Material, Material] | None = None) -> FaceSet:
    """An upright box standing on height ``z0``.

    Args:
        center_xy: footprint centre (world x, y).
        size: ``(length along heading, width, height)`` metres.
        yaw: heading (radians, from world x towards y); "front" is the +heading face.
        side / front / back / top: materials; front/back default to ``side``;
            ``sides`` overrides the (left, right) long faces. Vertical faces have
            ``v`` up from the bottom edge; ``u`` runs left to right seen from outside.
        bottom: also emit the bottom face (objects that float, e.g. a table top).
    """
    L, W, H = (float(s) for s in size)
    if min(L, W, H) <= 0:
        raise SynthError(f"box: sizes must be positive, got {size}")
    c = np.array([center_xy[0], center_xy[1], z0 + H / 2])
    a1 = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    a2 = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
    a3 = np.array([0.0, 0.0, 1.0])
    hl, hw, hh = a1 * L / 2, a2 * W / 2, a3 * H / 2
    left, right = sides if sides is not None else (side, side)
    faces = [
        quad(c + hl - hw - hh, a2 * W, a3 * H, front or side),      # +a1 (front)
        quad(c - hl + hw - hh, -a2 * W, a3 * H, back or side),      # -a1 (back)
        quad(c + hw + hl - hh, -a1 * L, a3 * H, left),              # +a2 (left)
        quad(c - hw - hl - hh, a1 * L, a3 * H, right),              # -a2 (right)
        quad(c - hl - hw + hh, a1 * L, a2 * W, top or side),        # top
    ]
    if bottom:
        faces.append(quad(c - hl - hw - hh, a2 * W, a1 * L, side))
    return FaceSet.concat(faces)


@lru_cache(maxsize=8)
def _rays(fx: float, fy: float, cx: float, cy: float, w: int, h: int) -> np.ndarray:
    """``[H,W,3] float32`` camera-frame rays with z = 1 through pixel centres."""
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    r = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1)
    r.setflags(write=False)
    return r.astype(np.float32)


def _clip_near(poly: np.ndarray, near: float) -> np.ndarray:
    """Clip a camera-frame polygon ``[n,3]`` to ``z >= near`` (Sutherland-Hodgman)."""
    out = []
    n = len(poly)
    for k in range(n):
        a, b = poly[k], poly[(k + 1) % n]
        ina, inb = a[2] >= near, b[2] >= near
        if ina:
            out.append(a)
        if ina != inb:
            t = (near - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.array(out) if out else np.zeros((0, 3))


# mild display gamma as a lookup table (a float power over every pixel is slow)
_GAMMA_LUT = (np.linspace(0.0, 1.0, 1024) ** (1 / 1.1) * 255.0 + 0.5).astype(np.uint8)


@dataclass
class RenderOutput:
    """``rgb [H,W,3] uint8`` (None for depth-only renders), ``depth_m [H,W] float32``
    (z-depth, 0 = no surface), ``face_id [H,W] int32`` (-1 = none)."""

    rgb: np.ndarray | None
    depth_m: np.ndarray
    face_id: np.ndarray


def render(faces: FaceSet, T_world_cam: np.ndarray, K: CameraIntrinsics, ctx: tx.ShadeContext | None = None,
           *, near_m: float = 0.05, far_m: float = 400.0, with_rgb: bool = True) -> RenderOutput:
    """Render ``faces`` seen from a camera at ``T_world_cam`` (camera-to-world, OpenCV axes)."""
    T = np.asarray(T_world_cam, float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise SynthError(f"render: T_world_cam must be a finite 4x4 matrix, got shape {T.shape}")
    ctx = ctx or tx.ShadeContext()
    W, H = int(K.width), int(K.height)
    rays = _rays(float(K.fx), float(K.fy), float(K.cx), float(K.cy), W, H)
    R_wc, C = T[:3, :3], T[:3, 3]
    zbuf = np.full((H, W), np.inf, np.float32)
    fid = np.full((H, W), -1, np.int32)
    ubuf = np.zeros((H, W), np.float32)
    vbuf = np.zeros((H, W), np.float32)
    if len(faces):
        o_c = (faces.origin - C) @ R_wc
        eu_c = faces.eu @ R_wc
        ev_c = faces.ev @ R_wc
        n_c = np.cross(eu_c, ev_c)
        lu, lv = faces.size[:, 0], faces.size[:, 1]
        # back-face culling: the camera (origin) must be on the normal side
        front = (-o_c * n_c).sum(1) > 1e-9
        corners = np.stack([o_c, o_c + eu_c * lu[:, None], o_c + eu_c * lu[:, None] + ev_c * lv[:, None],
                            o_c + ev_c * lv[:, None]], 1)  # [F,4,3]
        x, y, z = corners[..., 0], corners[..., 1], corners[..., 2]
        planes = [z - near_m, far_m - z, K.fx * x + (K.cx + 0.5) * z, -K.fx * x + (W - 0.5 - K.cx) * z,
                  K.fy * y + (K.cy + 0.5) * z, -K.fy * y + (H - 0.5 - K.cy) * z]
        visible = front.copy()
        for p in planes:
            visible &= np.any(p >= 0, axis=1)
        for f in np.flatnonzero(visible):
            poly = corners[f]
            if np.any(poly[:, 2] < near_m):
                poly = _clip_near(poly, near_m)
                if len(poly) < 3:
                    continue
            px = K.fx * poly[:, 0] / poly[:, 2] + K.cx
            py = K.fy * poly[:, 1] / poly[:, 2] + K.cy
            x0, x1 = max(int(np.floor(px.min())), 0), min(int(np.ceil(px.max())) + 1, W)
            y0, y1 = max(int(np.floor(py.min())), 0), min(int(np.ceil(py.max())) + 1, H)
            if x0 >= x1 or y0 >= y1:
                continue
            d = rays[y0:y1, x0:x1]
            n = n_c[f].astype(np.float32)
            denom = d @ n
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.float32(o_c[f] @ n_c[f]) / denom
            e1, e2, o = eu_c[f].astype(np.float32), ev_c[f].astype(np.float32), o_c[f].astype(np.float32)
            uu = t * (d @ e1) - np.float32(o @ e1)
            vv = t * (d @ e2) - np.float32(o @ e2)
            zb = zbuf[y0:y1, x0:x1]
            m = (denom < 0) & (t > near_m) & (t < zb) & (uu >= 0) & (uu <= lu[f]) & (vv >= 0) & (vv <= lv[f])
            if not m.any():
                continue
            np.copyto(zb, t, where=m)
            np.copyto(fid[y0:y1, x0:x1], f, where=m)
            np.copyto(ubuf[y0:y1, x0:x1], uu, where=m)
            np.copyto(vbuf[y0:y1, x0:x1], vv, where=m)
    hit = fid >= 0
    depth = np.where(hit, zbuf, 0.0).astype(np.float32)
    if not with_rgb:
        return RenderOutput(None, depth, fid)
    img = np.zeros((H * W, 3), np.float32)
    rays_flat = rays.reshape(-1, 3)
    horizon = np.array([0.78, 0.84, 0.9])
    if ctx.outdoor:
        sky_idx = np.flatnonzero(~hit.ravel())
        if sky_idx.size:
            dz = rays_flat[sky_idx] @ R_wc.T.astype(np.float32)
            dz /= np.sqrt((dz * dz).sum(1))[:, None]
            el = np.clip(dz[:, 2], -0.2, 1.0)
            sky = horizon + (np.array([0.32, 0.52, 0.86]) - horizon) * np.sqrt(np.clip(el, 0, 1))[:, None]
            # clouds at infinity: a function of direction only (no parallax, no depth)
            k = np.maximum(dz[:, 2], 0.05)
            cl = fbm(dz[:, 0] / k * 3.0, dz[:, 1] / k * 3.0, np.full(len(k), 0.002), 0.4, 4, 999)
            sky = mix(sky, np.array([0.95, 0.95, 0.97]), np.clip(cl * 0.7, 0, 0.8) * np.clip(el * 4, 0, 1))
            img[sky_idx] = sky
    idx = np.flatnonzero(hit.ravel())
    if idx.size:
        f_px = fid.ravel()[idx]
        z = depth.ravel()[idx]
        r_px = rays_flat[idx]
        R32 = R_wc.astype(np.float32)
        # float32 [N,3] x [3,3]: numpy's float64 path for this shape is far slower
        xw = ((r_px * z[:, None]) @ R32.T).astype(np.float64) + C
        ray_len = np.sqrt((r_px * r_px).sum(1))
        cos_t = np.abs((r_px * n_c[f_px].astype(np.float32)).sum(1)) / ray_len
        foot = z * ray_len / K.fx / np.sqrt(np.maximum(cos_t, 0.02))
        light_dir = np.asarray(ctx.light_dir, float)
        light_dir = light_dir / np.linalg.norm(light_dir)
        lam = np.clip(faces.normal @ light_dir, 0, None)
        face_light = (0.5 + 0.6 * lam) if ctx.outdoor else (0.72 + 0.35 * lam)
        kinds = faces.kind[f_px]
        col = np.zeros((idx.size, 3), np.float32)
        u_px, v_px = ubuf.ravel()[idx], vbuf.ravel()[idx]
        xw = xw.astype(np.float32)  # world coordinates within a few hundred metres: float32 is ample
        foot = foot.astype(np.float32)
        size32, color32, prm32 = (a.astype(np.float32) for a in (faces.size, faces.color, faces.prm))
        for kd in np.flatnonzero(np.bincount(kinds, minlength=len(SHADERS))):
            sel = np.flatnonzero(kinds == kd)
            fs = f_px[sel]
            si = tx.ShadeInput(u=u_px[sel], v=v_px[sel], lu=size32[fs, 0], lv=size32[fs, 1],
                               xw=xw[sel], foot=foot[sel], seed=PerFace(fs, faces.seed),
                               color=color32[fs], prm=prm32[fs], ctx=ctx)
            col[sel] = SHADERS[int(kd)](si)
        col *= face_light[f_px][:, None].astype(np.float32)
        if ctx.outdoor:
            haze = (1.0 - np.exp(-z / 350.0))[:, None]
            col = col * (1 - haze) + horizon.astype(np.float32) * haze
        img[idx] = col
    img = img.reshape(H, W, 3)
    rgb = _GAMMA_LUT[(np.clip(img, 0.0, 1.0) * 1023.0 + 0.5).astype(np.int16)]
    return RenderOutput(rgb, depth, fid)
