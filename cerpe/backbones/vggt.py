"""VGGT (Wang et al., CVPR 2025) as the paper's :class:`~cerpe.protocols.PoseBackbone`.

The model code comes from the upstream ``vggt`` package (not on PyPI; install
it from its repository, see ``docs/PAPER_MODELS.md``) and is imported lazily.
Weights are a user-supplied local file (``model.pt`` or ``model.safetensors``
of VGGT-1B / VGGT-1B-Commercial). Everything this adapter *converts* is a pure
numpy function below with no ``vggt`` import, so it is tested without the model.

Conventions handled here (from upstream's ``load_fn.py``, ``pose_enc.py``):

* Input ``[S,3,H,W]`` in ``[0,1]``; ImageNet normalisation happens inside the model.
  ``crop`` mode: width 518, height ``round(H*518/W/14)*14``, centre-cropped to 518
  if taller. ``pad`` mode: longest side 518, the other rounded to a multiple of 14,
  padded to 518x518 with white. Resizing is PIL bicubic, as upstream. Views of
  different aspect end up with different sizes; like upstream, they are padded
  (white, centred) to the largest, and that padding enters the bookkeeping.
* ``pose_enc [B,S,9]`` = translation (3), quaternion **XYZW** (scalar last),
  ``fov_h``, ``fov_w``. Extrinsics ``[R|t]`` are OpenCV **camera-from-world**;
  frame 0 is the world; the scene is normalised (arbitrary unit). Intrinsics:
  ``fy = (H/2)/tan(fov_h/2)``, ``fx = (W/2)/tan(fov_w/2)``, principal point at
  ``(W/2, H/2)`` of the network canvas. We read that centre in the
  corner-origin convention (where ``W/2`` *is* the centre) and convert to
  ours (pixel centres at integers): ``c_index = c_corner - 0.5``.
* Output: ``T_frame_cam = inv([R|t])`` (camera-to-frame; the frame is camera 0
  of this pass), intrinsics of the *input* image, depth and confidence
  resampled back to the input resolution; input pixels outside the network
  canvas (cropped away) get depth 0 and confidence 0.

Pixel bookkeeping (:class:`CanvasGeometry`), with pixel centres at integers:
``u_net = (u + 0.5) * sx - 0.5 + pad_left``, ``v_net = (v + 0.5) * sy - 0.5 - crop_top + pad_top``,
``sx = w_resized / W``, ``sy = h_resized / H``.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import cv2
import numpy as np
import torch

from ..geometry import matrix_to_quat_xyzw, quat_xyzw_to_matrix, se3_inverse
from ..config import merge_conf
from ..protocols import BackboneOutput, View
from ..scene import CameraIntrinsics, SceneError
from .weights import (
    PaperModelError,
    autocast_dtype,
    load_checkpoint,
    load_state_dict_strict,
    peak_vram_bytes,
    reset_peak_vram,
    select_device,
)

logger = logging.getLogger(__name__)

TARGET_SIZE = 518
PATCH = 14


class VGGTError(PaperModelError):
    """Bad input to the VGGT adapter, missing package, or a wrong checkpoint."""


# ----------------------------------------------------------------------------- pure bookkeeping
@dataclass(frozen=True)
class CanvasGeometry:
    """Where an input image of size ``in_hw`` lies on the ``net_hw`` network canvas.

    Attributes:
        in_hw: input ``(H, W)``.
        resized_hw: size after the resize ``(h_r, w_r)``.
        crop_top: rows of the resized image cut from its top (crop mode).
        pad_top, pad_left: offset of the (cropped) resized image on the canvas.
        net_hw: canvas size ``(H_n, W_n)``, multiples of 14.
    """

    in_hw: tuple[int, int]
    resized_hw: tuple[int, int]
    crop_top: int
    pad_top: int
    pad_left: int
    net_hw: tuple[int, int]

    @property
    def sx(self) -> float:
        return self.resized_hw[1] / self.in_hw[1]

    @property
    def sy(self) -> float:
        return self.resized_hw[0] / self.in_hw[0]

    @property
    def visible_rows(self) -> int:
        """Rows of the resized image that are on the canvas."""
        return min(self.resized_hw[0] - self.crop_top, self.net_hw[0] - self.pad_top)

    def net_from_input(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Input pixel coordinates -> canvas coordinates (pixel centres at integers)."""
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        return (u + 0.5) * self.sx - 0.5 + self.pad_left, (v + 0.5) * self.sy - 0.5 - self.crop_top + self.pad_top

    def input_from_net(self, u_net: np.ndarray, v_net: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Canvas coordinates -> input pixel coordinates (inverse of :meth:`net_from_input`)."""
        u_net = np.asarray(u_net, dtype=np.float64)
        v_net = np.asarray(v_net, dtype=np.float64)
        return ((u_net - self.pad_left + 0.5) / self.sx - 0.5,
                (v_net - self.pad_top + self.crop_top + 0.5) / self.sy - 0.5)

    def with_extra_pad(self, top: int, left: int, net_hw: tuple[int, int]) -> "CanvasGeometry":
        return CanvasGeometry(self.in_hw, self.resized_hw, self.crop_top, self.pad_top + top,
                              self.pad_left + left, net_hw)


def canvas_geometry(in_hw: tuple[int, int], mode: str = "crop", target: int = TARGET_SIZE,
                    patch: int = PATCH) -> CanvasGeometry:
    """Upstream's ``load_and_preprocess_images`` sizes for one image of size ``in_hw``."""
    H, W = int(in_hw[0]), int(in_hw[1])
    if H <= 0 or W <= 0:
        raise VGGTError(f"VGGT input: empty image {H}x{W}")
    if mode == "crop":
        w_r = target
        h_r = round(H * (w_r / W) / patch) * patch
    elif mode == "pad":
        if W >= H:
            w_r = target
            h_r = round(H * (w_r / W) / patch) * patch
        else:
            h_r = target
            w_r = round(W * (h_r / H) / patch) * patch
    else:
        raise VGGTError(f"VGGT preprocessing mode {mode!r}: use 'crop' or 'pad'")
    if h_r <= 0 or w_r <= 0:
        raise VGGTError(f"VGGT input {W}x{H}: aspect ratio too extreme for {mode} mode")
    crop_top = (h_r - target) // 2 if (mode == "crop" and h_r > target) else 0
    h_vis = min(h_r, target) if mode == "crop" else h_r
    if mode == "pad":
        pad_top, pad_left = (target - h_r) // 2, (target - w_r) // 2
        net_hw = (target, target)
    else:
        pad_top, pad_left = 0, 0
        net_hw = (h_vis, w_r)
    return CanvasGeometry((H, W), (h_r, w_r), crop_top, pad_top, pad_left, net_hw)


def unify_canvases(geoms: Sequence[CanvasGeometry]) -> list[CanvasGeometry]:
    """Pad every canvas (centred) to the largest, as upstream does for mixed shapes."""
    Hm = max(g.net_hw[0] for g in geoms)
    Wm = max(g.net_hw[1] for g in geoms)
    return [g.with_extra_pad((Hm - g.net_hw[0]) // 2, (Wm - g.net_hw[1]) // 2, (Hm, Wm)) for g in geoms]


def render_canvas(image: np.ndarray, geom: CanvasGeometry) -> np.ndarray:
    """``[H,W,3] uint8`` -> ``[3,H_n,W_n] float32`` in ``[0,1]`` on the white canvas (PIL bicubic)."""
    from PIL import Image

    h_r, w_r = geom.resized_hw
    resized = np.asarray(Image.fromarray(image).resize((w_r, h_r), Image.Resampling.BICUBIC), dtype=np.float32) / 255.0
    canvas = np.ones((geom.net_hw[0], geom.net_hw[1], 3), dtype=np.float32)
    rows = geom.visible_rows
    canvas[geom.pad_top:geom.pad_top + rows, geom.pad_left:geom.pad_left + w_r] = \
        resized[geom.crop_top:geom.crop_top + rows]
    return canvas.transpose(2, 0, 1)


def map_to_input(net_map: np.ndarray, geom: CanvasGeometry, interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
    """Resample a canvas-sized map ``[H_n,W_n]`` to the input image ``[H,W]``.

    Input pixels whose canvas position falls outside the image's own region of
    the canvas (cropped rows, padding) get 0.
    """
    H, W = geom.in_hw
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    un, vn = geom.net_from_input(u, v)
    x0, x1 = geom.pad_left - 0.5, geom.pad_left + geom.resized_hw[1] - 0.5
    y0, y1 = geom.pad_top - 0.5, geom.pad_top + geom.visible_rows - 0.5
    inside = (un >= x0) & (un <= x1) & (vn >= y0) & (vn <= y1)
    out = cv2.remap(np.ascontiguousarray(net_map, dtype=np.float32), un.astype(np.float32), vn.astype(np.float32),
                    interpolation, borderMode=cv2.BORDER_REPLICATE)
    out[~inside] = 0.0
    return out


def decode_pose_encoding(pose_enc: np.ndarray, net_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """VGGT ``pose_enc [S,9]`` -> camera-from-world ``[S,4,4]`` and canvas ``K [S,3,3]`` (corner origin).

    Layout: ``t (3) | q_xyzw (4) | fov_h | fov_w``. The quaternion is normalised
    (the head's output is not exactly unit).
    """
    pose_enc = np.asarray(pose_enc, dtype=np.float64)
    if pose_enc.ndim != 2 or pose_enc.shape[1] != 9:
        raise VGGTError(f"pose_enc: expected [S,9], got {pose_enc.shape}")
    S = pose_enc.shape[0]
    T = np.tile(np.eye(4), (S, 1, 1))
    q = pose_enc[:, 3:7]
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    ok = np.isfinite(pose_enc).all(axis=1) & (norm[:, 0] > 1e-8)
    T[~ok] = np.nan
    if ok.any():
        T[ok, :3, :3] = quat_xyzw_to_matrix(q[ok] / norm[ok])
        T[ok, :3, 3] = pose_enc[ok, :3]
    H, W = net_hw
    K = np.zeros((S, 3, 3))
    with np.errstate(divide="ignore", invalid="ignore"):  # fov 0 -> inf focal: caller drops those intrinsics
        K[:, 0, 0] = (W / 2.0) / np.tan(pose_enc[:, 8] / 2.0)
        K[:, 1, 1] = (H / 2.0) / np.tan(pose_enc[:, 7] / 2.0)
    K[:, 0, 2] = W / 2.0
    K[:, 1, 2] = H / 2.0
    K[:, 2, 2] = 1.0
    return T, K


def encode_pose(T_cam_world: np.ndarray, K: np.ndarray, net_hw: tuple[int, int]) -> np.ndarray:
    """Inverse of :func:`decode_pose_encoding` (upstream's ``extri_intri_to_pose_encoding``); for tests."""
    T_cam_world = np.asarray(T_cam_world, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    H, W = net_hw
    q = matrix_to_quat_xyzw(T_cam_world[:, :3, :3])
    fov_h = 2 * np.arctan((H / 2) / K[:, 1, 1])
    fov_w = 2 * np.arctan((W / 2) / K[:, 0, 0])
    return np.concatenate([T_cam_world[:, :3, 3], q, fov_h[:, None], fov_w[:, None]], axis=1)


def intrinsics_to_input(K_net: np.ndarray, geom: CanvasGeometry) -> CameraIntrinsics:
    """Canvas ``K`` (principal point in corner-origin convention) -> intrinsics of the input image."""
    cu, cv = geom.input_from_net(K_net[0, 2] - 0.5, K_net[1, 2] - 0.5)
    H, W = geom.in_hw
    return CameraIntrinsics(fx=float(K_net[0, 0] / geom.sx), fy=float(K_net[1, 1] / geom.sy),
                            cx=float(cu), cy=float(cv), width=W, height=H)


# ----------------------------------------------------------------------------- adapter
def build_vggt_model(checkpoint: str | Path | None = None) -> torch.nn.Module:
    """Upstream ``VGGT()`` (VGGT-1B architecture) with weights from a local file.

    Raises:
        VGGTError: ``vggt`` not importable (with the install command), or the
            checkpoint does not match (listing a few keys).
    """
    try:
        from vggt.models.vggt import VGGT
    except ModuleNotFoundError as exc:
        raise VGGTError(
            f"VGGT: cannot import the upstream model ({exc}); install it with: git clone "
            f"https://github.com/facebookresearch/vggt && pip install --no-deps -e vggt && "
            f"pip install huggingface_hub einops safetensors") from None
    model = VGGT()
    if checkpoint:
        path = Path(checkpoint).expanduser()
        sd = load_checkpoint(path, "VGGT-1B")
        sd = sd.get("state_dict", sd)
        sd = {k[len("model."):] if k.startswith("model.") else k: v for k, v in sd.items()}
        try:
            load_state_dict_strict(model, sd, path, "VGGT-1B")
        except PaperModelError as exc:
            raise VGGTError(str(exc)) from None
    return model


class VGGTBackbone:
    """:class:`~cerpe.protocols.PoseBackbone` running VGGT once over all views of a call.

    Args:
        conf: see :attr:`default_conf`.
        model: an already built upstream ``VGGT`` module (tests use a small
            random-weight one); otherwise built from ``conf["checkpoint"]``.

    After each :meth:`infer`, ``last_stats`` holds the device, autocast dtype,
    number of views and ``vram_peak_bytes`` (``torch.cuda.max_memory_allocated``
    of the pass; None on CPU); the same numbers go into ``BackboneOutput.extra``.
    """

    default_conf: dict[str, Any] = {
        "checkpoint": None,
        "device": "auto",
        "mode": "crop",  # crop | pad (upstream's preprocessing modes)
        "target_size": TARGET_SIZE,  # 518 as trained; smaller only for tests/speed experiments
        "min_conf": 0.0,  # depth with confidence below this is set to 0 (VGGT's conf >= 1)
        "max_views": 16,  # more views than this in one call is a programming error
    }

    def __init__(self, conf: Mapping[str, Any] | None = None, model: torch.nn.Module | None = None) -> None:
        self.conf = merge_conf(self.default_conf, conf, "VGGT conf")
        self.device = select_device(self.conf["device"])
        self.dtype = autocast_dtype(self.device)
        if model is None:
            if not self.conf["checkpoint"]:
                raise VGGTError("VGGT: no checkpoint given (vggt.checkpoint); see docs/PAPER_MODELS.md")
            model = build_vggt_model(self.conf["checkpoint"])
        self.model = model.eval().to(self.device)
        self.last_stats: dict[str, Any] = {}

    def _check(self, views: Sequence[View]) -> None:
        if not views:
            raise VGGTError("VGGT: infer() needs at least one view")
        if len(views) > self.conf["max_views"]:
            raise VGGTError(f"VGGT: {len(views)} views in one pass exceeds max_views={self.conf['max_views']}")
        for i, v in enumerate(views):
            img = v.image
            if not isinstance(img, np.ndarray) or img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
                desc = f"{img.shape} {img.dtype}" if isinstance(img, np.ndarray) else type(img).__name__
                raise VGGTError(f"VGGT: view {i} ({v.key!r}): expected [H,W,3] uint8 RGB, got {desc}")

    def infer(self, views: Sequence[View]) -> BackboneOutput:
        """One joint pass over ``views`` (current, memory newest first, collaborators)."""
        self._check(views)
        t0 = time.perf_counter()
        geoms = unify_canvases([canvas_geometry(v.image.shape[:2], self.conf["mode"], int(self.conf["target_size"])) for v in views])
        x = torch.from_numpy(np.stack([render_canvas(v.image, g) for v, g in zip(views, geoms)]))
        x = x.to(self.device)
        t1 = time.perf_counter()
        reset_peak_vram(self.device)
        with torch.inference_mode():
            if self.dtype is not None:
                with torch.autocast(device_type="cuda", dtype=self.dtype):
                    pred = self.model(x)
            else:
                pred = self.model(x)
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        t2 = time.perf_counter()
        out = self._convert(pred, views, geoms)
        t3 = time.perf_counter()
        vram = peak_vram_bytes(self.device)
        self.last_stats = {"device": str(self.device), "dtype": str(self.dtype or torch.float32),
                           "n_views": len(views), "vram_peak_bytes": vram}
        out.timings_s.update({"vggt_preprocess": t1 - t0, "vggt_forward": t2 - t1, "vggt_postprocess": t3 - t2})
        out.extra.update({"vggt_vram_peak_bytes": float(vram) if vram is not None else float("nan"),
                          "vggt_n_views": float(len(views))})
        logger.debug("VGGT pass: %d views, %.3f s, peak VRAM %s", len(views), t2 - t1, vram)
        return out

    def _convert(self, pred: Mapping[str, torch.Tensor], views: Sequence[View],
                 geoms: Sequence[CanvasGeometry]) -> BackboneOutput:
        for k in ("pose_enc", "depth", "depth_conf"):
            if k not in pred:
                raise VGGTError(f"VGGT output lacks {k!r}: a model built without its camera/depth head?")
        S = len(views)
        pose_enc = pred["pose_enc"].float().cpu().numpy().reshape(S, 9)
        depth = pred["depth"].float().cpu().numpy().reshape(S, *geoms[0].net_hw)
        conf = pred["depth_conf"].float().cpu().numpy().reshape(S, *geoms[0].net_hw)
        T_cam_world, K_net = decode_pose_encoding(pose_enc, geoms[0].net_hw)
        valid = np.isfinite(T_cam_world).all(axis=(1, 2))
        T_frame_cam = np.full((S, 4, 4), np.nan)
        if valid.any():
            T_frame_cam[valid] = se3_inverse(T_cam_world[valid])
        reasons = ["" if ok else "non-finite VGGT pose" for ok in valid]
        depths, confs, intr = [], [], []
        for s, g in enumerate(geoms):
            d = np.where(np.isfinite(depth[s]) & (depth[s] > 0), depth[s], 0.0)
            c = np.where(np.isfinite(conf[s]) & (d > 0), conf[s], 0.0)
            if self.conf["min_conf"] > 0:
                d = np.where(c >= self.conf["min_conf"], d, 0.0)
                c = np.where(d > 0, c, 0.0)
            d_in = map_to_input(d, g)
            c_in = map_to_input(c, g)
            # Bilinear blending with zeroed pixels would fake small depths: keep only
            # pixels whose neighbourhood was fully valid.
            m_in = map_to_input((d > 0).astype(np.float32), g) > 0.999
            depths.append(np.where(m_in, d_in, 0.0).astype(np.float32))
            confs.append(np.where(m_in, c_in, 0.0).astype(np.float32))
            try:
                intr.append(intrinsics_to_input(K_net[s], g) if valid[s] else None)
            except SceneError:  # non-finite fov: the view keeps its pose, loses intrinsics
                intr.append(None)
        return BackboneOutput(T_frame_cam=T_frame_cam, valid=valid, depth=depths, depth_conf=confs,
                              intrinsics=intr, reasons=reasons)
