"""Training-free SALAD-style global descriptor over XFeat local features.

Implements :class:`cerpe.protocols.DescriptorEncoder` for the offline profile. The
paper aggregates DINOv2 patch features with a *trained* SALAD head; no such weights
exist here. So this keeps SALAD's aggregation and replaces the learned parts. The
aggregation is Sinkhorn transport of the local features onto ``m`` clusters plus a
dustbin, per-cluster sums and L2 normalisation, a global token, and L2 normalisation
of the whole. The learned parts become:

* local features: the XFeat keypoint descriptors (the ones the pose backbone
  matches, the best :data:`MAX_KEYPOINTS`);
* scores: ``BETA * cos(f_i, c_k)`` with spherical k-means centres ``c_k`` fitted on
  synthetic renders of development seeds (``cerpe/data/xfeat_salad_centres.npz``,
  made by ``cerpe fit descriptor``); the dustbin scores ``BETA * DUSTBIN_COS``;
* aggregation: the residuals ``f_i - c_k`` summed per cluster (NetVLAD's residuals
  with SALAD's transport plan as soft assignment), square-rooted (:data:`POWER`):
  without a learned projection a cluster's plain sum mostly re-describes the
  cluster's own direction;
* the global token: a square-rooted hue x saturation x value histogram
  (:data:`COLOUR_BINS`) carrying ``TOKEN_WEIGHT2 / (TOKEN_WEIGHT2 + 1)`` of the
  similarity: XFeat describes grey-level texture only, while places built from a
  few repeated textures differ in colour;
* centring (``mean``): the mean descriptor of development renders (``cerpe/data/xfeat_salad_mean.npz``,
  made by ``cerpe fit descriptor --descriptor-mean``) is subtracted and the result
  re-normalised, as NetVLAD's PCA whitening removes its training mean. What every view
  of these worlds shares (road, walls, sky) then no longer counts as overlap
  (``cerpe fit thresholds`` measures the co-visibility ROC AUC). ``mean: none``
  is the plain aggregate.

Size ``m*64 + g`` (64 x 64 + 4096 = 8192), no more than the paper's 8448, so a
descriptor frame is no larger than the paper's. How well it ranks overlap is printed
by :func:`cerpe.pipeline.evaluate.gate_quality` for every run.

Thresholds ``tau``, ``tau_m``, ``tau_k`` come from
``cerpe/data/xfeat_salad_thresholds.json``, written by
``cerpe fit thresholds`` on encounters of a development seed. ``tau``
maximises F1 of ``similarity >= tau`` against "overlap >= 0.2". ``tau_m`` and
``tau_k`` are low quantiles of the similarity of consecutive frames and of frames
``Delta_k`` apart.

Images without usable texture (grey-level std below :data:`cerpe.protocols.BLANK_STD`: blank,
black, constant grey; or no more keypoints than clusters) get no content
descriptor. :meth:`describe` returns a unit vector drawn from a generator seeded by
the view key, nearly orthogonal to every other descriptor, so it can never open the
gate. :meth:`flags` says ``{"low-texture"}`` for the algorithm to act on and
count. Malformed or too small images raise
:class:`~cerpe.backbones.xfeat.ImageInputError`.
"""
from __future__ import annotations

import json
import logging
import time
import zlib
from pathlib import Path
from typing import Hashable, Mapping

import numpy as np

from ..protocols import BLANK_STD, BackboneError, View
from .cache import LRUCache, content_key
from .config import DescriptorConfig
from .xfeat import XFeatEncoder, XFeatFeatures, check_image, grey_std, shared_encoder

logger = logging.getLogger(__name__)

CENTRES_FILE = "xfeat_salad_centres.npz"
MEAN_FILE = "xfeat_salad_mean.npz"
THRESHOLDS_FILE = "xfeat_salad_thresholds.json"


class DescriptorError(BackboneError):
    """The descriptor cannot be set up (missing/corrupt centres file) or got a malformed input."""


def data_path(name: str) -> Path:
    """Path of a file shipped in ``cerpe/data``, found from this file (not ``importlib.resources``: with
    the editable install, a folder named ``cerpe`` in the working directory, e.g. a run folder, makes
    ``cerpe`` a namespace package whose resources are that folder)."""
    return Path(__file__).resolve().parents[1] / "data" / name


def _read_npz(path: Path, what: str, fields: tuple[str, ...], hint: str) -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` at ``path``; :class:`DescriptorError` naming the file (and the
    field) when it is missing (with ``hint``), unreadable, or lacks one of ``fields``."""
    if not path.is_file():
        raise DescriptorError(f"{what}: file not found: {path} ({hint})")
    try:
        with np.load(path) as z:
            data = {k: np.asarray(z[k]) for k in z.files}
    except Exception as exc:
        raise DescriptorError(f"{what}: cannot read {path} (truncated or corrupt?): {exc}") from None
    for name in fields:
        if name not in data:
            raise DescriptorError(f"{what}: {path} lacks field {name!r}")
    return data


def load_centres(path: str | Path | None = None) -> dict[str, np.ndarray]:
    """Load ``centres [m,64]`` and ``mean [64]`` from the shipped (or given) ``.npz``.

    Raises:
        DescriptorError: naming the file and the missing/bad field.
    """
    path = Path(path) if path else data_path(CENTRES_FILE)
    data = _read_npz(path, "descriptor centres", ("centres", "mean"), "run `cerpe fit descriptor` to create it")
    c, mu = data["centres"].astype(np.float32), data["mean"].astype(np.float32).ravel()
    if c.ndim != 2 or c.shape[1] != 64 or mu.shape != (64,) or not np.all(np.isfinite(c)) or not np.all(np.isfinite(mu)):
        raise DescriptorError(
            f"descriptor centres: {path}: field 'centres' must be finite [m,64] and 'mean' [64], "
            f"got {c.shape} and {mu.shape}")
    c = c / np.maximum(np.linalg.norm(c, axis=1, keepdims=True), 1e-12)
    data["centres"], data["mean"] = c, mu
    return data


def load_descriptor_mean(path: str | Path | None, dim: int) -> np.ndarray:
    """The ``[dim]`` mean descriptor subtracted before normalisation (see the module docstring).

    Raises:
        DescriptorError: naming the file and the field: missing or unreadable file, no
            ``mean`` field, non-finite values, or a length other than ``dim`` (a mean
            fitted for other centres or another token).
    """
    path = Path(path) if path else data_path(MEAN_FILE)
    data = _read_npz(path, "descriptor mean", ("mean",),
                     "run cerpe fit descriptor --descriptor-mean, or set mean: none")
    mu = data["mean"].astype(np.float32).ravel()
    if mu.shape != (dim,) or not np.all(np.isfinite(mu)):
        got = f"{mu.shape[0]}" + ("" if np.all(np.isfinite(mu)) else " non-finite")
        raise DescriptorError(f"descriptor mean: {path}: field 'mean' must be {dim} finite values (this "
                              f"descriptor's size), got {got}; refit it for these centres or set mean: none")
    return mu


def default_thresholds() -> dict[str, float]:
    """Calibrated thresholds from the shipped JSON, or conservative placeholders if absent."""
    path = data_path(THRESHOLDS_FILE)
    if path.is_file():
        try:
            with open(path) as fh:
                th = json.load(fh)["thresholds"]
            return {k: float(th[k]) for k in ("tau", "tau_m", "tau_k")}
        except Exception as exc:  # a broken shipped file must not silently change the gate
            raise DescriptorError(f"descriptor thresholds: cannot read {path}: {exc}") from None
    logger.warning("descriptor thresholds: %s missing; using uncalibrated defaults", path)
    return {"tau": 0.5, "tau_m": 0.9, "tau_k": 0.2}


# the aggregation (see the module docstring)
MAX_KEYPOINTS = 1024  # local features aggregated: the best keypoints by score
BETA = 100.0  # inverse temperature of the cosine scores
DUSTBIN_COS = 0.3  # cosine level of the dustbin score (BETA * DUSTBIN_COS)
POWER = 0.5  # signed power of each aggregated value (0.5: square root)
SINKHORN_ITERS = 3  # as SALAD
# the colour token: (hue, saturation, value) bins of the histogram of the image area-resized to
# COLOUR_SIZE (width, height); TOKEN_WEIGHT2: its squared weight relative to all cluster blocks together
COLOUR_BINS = (32, 16, 8)
COLOUR_SIZE = (160, 120)
TOKEN_WEIGHT2 = 1.0
CACHE_SIZE = 256  # descriptors kept (LRU, keyed by view key and pixels: a blank image's placeholder depends on the key)


class XFeatSaladDescriptor:
    """SALAD aggregation over XFeat features with k-means centres (no training).

    Args:
        conf: the fitted data it reads (:class:`~cerpe.backbones.config.DescriptorConfig`:
            ``centres``, ``mean``); every other setting is a module constant.
        encoder: the shared :class:`XFeatEncoder` (None: :func:`shared_encoder`'s default).
        thresholds: ``tau``, ``tau_m``, ``tau_k`` for this descriptor (None: the calibrated
            values in ``cerpe/data/xfeat_salad_thresholds.json``), read by the algorithm as
            :attr:`thresholds` where its configuration gives none.
    """

    def __init__(self, conf: DescriptorConfig | None = None, encoder: XFeatEncoder | None = None,
                 thresholds: Mapping[str, float] | None = None) -> None:
        self.conf = conf or DescriptorConfig()
        self.encoder = encoder or shared_encoder()
        data = load_centres(self.conf.centres)
        self.centres = data["centres"]
        self.mean = data["mean"]
        self.num_clusters = int(self.centres.shape[0])
        self.token_dim = int(np.prod(COLOUR_BINS))
        self.dim = self.num_clusters * 64 + self.token_dim
        mean = self.conf.mean
        self.descriptor_mean: np.ndarray | None = (
            None if mean == "none" else load_descriptor_mean(None if mean == "shipped" else mean, self.dim))
        th = thresholds or default_thresholds()
        self.thresholds: dict[str, float] = {k: float(th[k]) for k in ("tau", "tau_m", "tau_k")}
        self._cache: LRUCache[tuple[np.ndarray, frozenset[str]]] = LRUCache(CACHE_SIZE)
        # split of the last describe() call (wall; CPU of the calling thread), read by cerpe.algorithm for
        # its stage timings
        self.last_timings_s: dict[str, float] = {"encode": 0.0, "descriptor": 0.0}
        self.last_cpu_s: dict[str, float] = {"encode": 0.0, "descriptor": 0.0}

    def flags(self, view: View) -> frozenset[str]:
        """``{"low-texture"}`` when ``view``'s image has no usable texture (see the module
        docstring), else empty. A function of the pixels: the same image gives the same
        flags whether or not :meth:`describe` saw it first."""
        return self._describe(view, timed=False)[1]

    def clear_cache(self) -> None:
        self._cache.clear()

    def wire_bytes(self) -> dict[str, int]:
        """Exact :class:`~cerpe.messages.DescriptorMessage` frame size per dtype."""
        from ..messages import DescriptorMessage

        return {dt: DescriptorMessage.wire_bytes(self.dim, dt) for dt in ("fp32", "fp16", "int8")}

    def describe(self, view: View) -> np.ndarray:
        """``[dim] float32`` unit descriptor of ``view.image`` (see the module docstring)."""
        return self._describe(view, timed=True)[0].copy()

    def _describe(self, view: View, timed: bool) -> tuple[np.ndarray, frozenset[str]]:
        """Descriptor and flags of ``view``, cached by its key and pixels; ``timed`` sets
        :attr:`last_timings_s`."""
        image = check_image(view.image, f"view {view.key!r}")
        ck = (view.key, content_key(image))
        t0, c0 = time.perf_counter(), time.thread_time()
        hit = self._cache.get(ck)
        if hit is not None:
            if timed:
                self.last_timings_s = {"encode": 0.0, "descriptor": time.perf_counter() - t0}
                self.last_cpu_s = {"encode": 0.0, "descriptor": time.thread_time() - c0}
            return hit
        t1, c1 = t0, c0
        std = grey_std(image)
        if std < BLANK_STD:
            d, flags = self._placeholder(view.key), frozenset({"low-texture"})
        else:
            feats = self.encoder.encode(view, std=std)
            t1, c1 = time.perf_counter(), time.thread_time()
            try:
                d, flags = self.centre(self.aggregate(feats, image)), frozenset()
            except DescriptorError:
                if self.local_features(feats).shape[0] > self.num_clusters:
                    raise
                # too few keypoints: no content to describe
                d, flags = self._placeholder(view.key), frozenset({"low-texture"})
        if timed:
            self.last_timings_s = {"encode": t1 - t0, "descriptor": time.perf_counter() - t1}
            self.last_cpu_s = {"encode": c1 - c0, "descriptor": time.thread_time() - c1}
        self._cache.put(ck, (d, flags))
        return d, flags

    def centre(self, d: np.ndarray) -> np.ndarray:
        """``[dim]`` unit descriptor minus the fitted mean, re-normalised (unchanged with ``mean: none``)."""
        if self.descriptor_mean is None:
            return d
        c = d - self.descriptor_mean
        n = float(np.linalg.norm(c))
        if not np.isfinite(n) or n < 1e-6:  # the mean itself: keep the aggregate rather than divide by ~0
            return d
        return (c / n).astype(np.float32)

    def _placeholder(self, key: Hashable) -> np.ndarray:
        seed = zlib.crc32(repr(key).encode()) ^ 0x5A1AD
        v = np.random.default_rng(seed).standard_normal(self.dim).astype(np.float32)
        return v / np.linalg.norm(v)

    @staticmethod
    def colour_token(image: np.ndarray) -> np.ndarray:
        """Square-rooted, L2-normalised HSV histogram ``[prod(COLOUR_BINS)]`` of an RGB image."""
        import cv2

        bins = list(COLOUR_BINS)
        w, h = COLOUR_SIZE
        small = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA) if image.shape[:2] != (h, w) else image
        hsv = cv2.cvtColor(small, cv2.COLOR_RGB2HSV)
        hist = cv2.calcHist([hsv], list(range(len(bins))), None, bins, [0, 180, 0, 256, 0, 256][:2 * len(bins)]).ravel()
        hist = np.sqrt(hist / max(float(hist.sum()), 1.0))
        return (hist / max(float(np.linalg.norm(hist)), 1e-12)).astype(np.float32)

    @staticmethod
    def local_features(feats: XFeatFeatures) -> np.ndarray:
        """``[n,64]`` unit local features to aggregate: the best :data:`MAX_KEYPOINTS` keypoint descriptors."""
        F = np.asarray(feats.descriptors[:MAX_KEYPOINTS], np.float32)
        return F / np.maximum(np.linalg.norm(F, axis=1, keepdims=True), 1e-12)

    def aggregate(self, feats: XFeatFeatures, image: np.ndarray) -> np.ndarray:
        """SALAD aggregation of one image's local features (+ its colour token) -> ``[dim]`` unit descriptor.

        Raises:
            DescriptorError: fewer local features than clusters (see :meth:`describe`, which
                turns this into a low-texture placeholder).
        """
        import torch

        from .salad import log_transport_plan

        F = self.local_features(feats)
        n, m = F.shape[0], self.num_clusters
        if n <= m:
            raise DescriptorError(f"descriptor: {n} local features, needs more than {m} (too little texture)")
        scores = BETA * (F @ self.centres.T)  # [n,m]
        with torch.inference_mode():
            logP = log_transport_plan(torch.from_numpy(np.ascontiguousarray(scores.T, np.float32))[None],
                                      float(BETA * DUSTBIN_COS), SINKHORN_ITERS)
            P = torch.exp(logP[0, :m] + float(np.log(n + m))).numpy().astype(np.float64)  # [m,n], unit mass per feature
        V = P @ F - P.sum(axis=1, keepdims=True) * self.centres  # [m,64] residuals
        V = np.sign(V) * np.abs(V) ** POWER
        V /= np.maximum(np.linalg.norm(V, axis=1, keepdims=True), 1e-12)
        # the m unit cluster blocks have squared norm m together; the token gets TOKEN_WEIGHT2 times that
        token = self.colour_token(image) * np.sqrt(TOKEN_WEIGHT2 * m)
        d = np.concatenate([token, V.T.ravel()])  # [l,m] row-major after the token, as upstream
        d /= max(float(np.linalg.norm(d)), 1e-12)
        if not np.all(np.isfinite(d)):
            raise DescriptorError("descriptor: aggregation produced non-finite values")
        return d.astype(np.float32)


def fit_centres(dense_maps: list[np.ndarray], num_clusters: int = 64, max_features: int = 200_000,
                seed: int = 0, iters: int = 50) -> dict[str, np.ndarray]:
    """Spherical k-means centres and the mean of L2-normalised dense XFeat features.

    Args:
        dense_maps: ``[64,...]`` features of the fitting images: dense maps ``[64,h,w]``
            (:attr:`XFeatFeatures.dense`) or transposed keypoint descriptors ``[64,n]``.
        num_clusters: ``m``.
        max_features: random subsample size (memory/time bound).
        seed: subsampling and initialisation seed (the result is deterministic).
        iters: Lloyd iterations.

    Returns:
        ``{"centres": [m,64] unit rows, "mean": [64]}`` (float32).
    """
    if not dense_maps:
        raise DescriptorError("fit_centres: no dense maps given")
    F = np.concatenate([d.reshape(64, -1).T for d in dense_maps], axis=0).astype(np.float32)
    F /= np.maximum(np.linalg.norm(F, axis=1, keepdims=True), 1e-12)
    rng = np.random.default_rng(seed)
    if len(F) > max_features:
        F = F[rng.choice(len(F), max_features, replace=False)]
    if len(F) < num_clusters:
        raise DescriptorError(f"fit_centres: {len(F)} features for {num_clusters} clusters")
    # k-means++ seeding on cosine distance, then spherical Lloyd iterations
    C = np.empty((num_clusters, 64), np.float32)
    C[0] = F[rng.integers(len(F))]
    dmin = 1.0 - F @ C[0]
    for k in range(1, num_clusters):
        p = np.maximum(dmin, 0) ** 2
        C[k] = F[rng.choice(len(F), p=p / p.sum())] if p.sum() > 0 else F[rng.integers(len(F))]
        dmin = np.minimum(dmin, 1.0 - F @ C[k])
    for _ in range(iters):
        assign = np.argmax(F @ C.T, axis=1)
        newC = np.zeros_like(C)
        np.add.at(newC, assign, F)
        empty = np.linalg.norm(newC, axis=1) < 1e-9
        newC[empty] = F[rng.choice(len(F), int(empty.sum()), replace=False)]
        newC /= np.linalg.norm(newC, axis=1, keepdims=True)
        if np.allclose(newC, C, atol=1e-6):
            C = newC
            break
        C = newC
    return {"centres": C.astype(np.float32), "mean": F.mean(axis=0).astype(np.float32)}
