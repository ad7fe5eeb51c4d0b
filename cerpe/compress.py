"""Compressed descriptor messages: a fitted linear projection, then int8 or product quantisation.

The global descriptor (8192 values for the offline descriptor, 8448 for SALAD) is
projected onto ``k`` principal directions of development descriptors (:func:`fit_projection`).
The fit is training-free: an eigen-decomposition, made once by ``cerpe fit projection``
and shipped beside the k-means centres. What those directions leave (the residual) is
projected onto ``random_dims`` random Gaussian directions (Johnson-Lindenstrauss: inner
products preserved in expectation, whatever the scene). The concatenation is L2-normalised.
A projection fitted on development data alone loses what unseen scenes have of their own,
and the gate then ranks their overlap worse; the random part keeps it. Two codecs quantise
the projected vector:

* ``pca-int8``: every value as int8 with one float32 scale per vector
  (code: ``scale f32 | int8 values``);
* ``pca-pq``: product quantisation into ``pq_m`` sub-vectors, one byte each (256
  centroids per sub-space, k-means by ``faiss``, fitted with the projection).

A code travels in a :class:`~cerpe.messages.DescriptorMessage` of dtype ``pca-int8`` /
``pca-pq`` with the projection's ``codebook`` id (CRC32 of its arrays). The gate scores
the cosine of the *decoded* vectors (:meth:`DescriptorCodec.wire`). A zero descriptor
(a blank frame) is the empty code and decodes to zeros. Decoding never raises on the
receiver's side. :meth:`DescriptorCodec.decode` returns ``(None, fault)`` for another
codec (``codec-mismatch``), another codebook (``codebook-mismatch``) or a code that does
not decode (``bad-code``). The robot counts ``descriptor:<fault>`` and keeps the gate closed.
"""
from __future__ import annotations

import json
import struct
import zlib
from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from .atomicio import atomic_write_npz
from .errors import CerpeError
from .messages import CODED_DESCRIPTOR_DTYPES, DescriptorMessage

CODECS: tuple[str, ...] = tuple(CODED_DESCRIPTOR_DTYPES)  # pca-int8, pca-pq
PROJECTION_FILE = "xfeat_salad_projection.npz"


class CompressError(CerpeError, ValueError):
    """A projection file that is missing, corrupt or inconsistent, or a bad codec argument."""


@dataclass(frozen=True)
class Projection:
    """A fitted projection and its product quantiser (see the module docstring).

    Shapes: ``components [k, D]`` (orthonormal rows: the leading principal directions of
    the second moment of development descriptors), ``pq_centroids [pq_m, 256, dims / pq_m]``.
    ``random_dims`` rows of a Gaussian matrix drawn from ``random_seed`` project the residual.
    They are not stored but drawn on load, and are part of :attr:`codebook`. So two robots
    whose NumPy draws differ see a codebook mismatch instead of wrong scores.
    """

    components: np.ndarray
    random_dims: int
    random_seed: int
    pq_centroids: np.ndarray
    thresholds: dict[str, dict[str, float]] = field(default_factory=dict)  # codec -> {"tau": ...}
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def dim(self) -> int:
        return int(self.components.shape[1])

    @property
    def dims(self) -> int:
        """Values of a projected descriptor: principal + random directions."""
        return int(self.components.shape[0] + self.random_dims)

    @property
    def pq_m(self) -> int:
        return int(self.pq_centroids.shape[0])

    @cached_property
    def random(self) -> np.ndarray:
        """``[random_dims, D]`` Gaussian rows scaled by ``1/sqrt(random_dims)`` (inner products unbiased)."""
        R = np.random.default_rng(self.random_seed).standard_normal((self.random_dims, self.dim), np.float32)
        return R / np.float32(np.sqrt(max(self.random_dims, 1)))

    @cached_property
    def codebook(self) -> int:
        """u32 id of this projection: CRC32 over its arrays (the drawn ones included)."""
        crc = zlib.crc32(struct.pack("<II", self.random_dims, self.random_seed))
        for a in (self.components, self.random, self.pq_centroids):
            crc = zlib.crc32(np.ascontiguousarray(a, np.float32).tobytes(), crc)
        return crc & 0xFFFFFFFF

    def project(self, d: np.ndarray) -> np.ndarray:
        """``[..., D]`` descriptors -> ``[..., dims]`` unit vectors ``[C d ; R (d - C^T C d)]`` (zeros stay zeros).

        The inner product of two projections is the descriptors' own on the principal
        subspace plus an unbiased random estimate of the rest (Johnson-Lindenstrauss):
        scenes unlike the development images keep their similarity.
        """
        d = np.asarray(d, np.float32)
        y = d @ self.components.T
        if self.random_dims:
            y = np.concatenate([y, (d - y @ self.components) @ self.random.T], axis=-1)
        n = np.linalg.norm(y, axis=-1, keepdims=True)
        return np.where(n > 0, y / np.maximum(n, 1e-30), 0.0).astype(np.float32)


def default_projection_path() -> Path:
    """The shipped projection file, found from this file (see :func:`cerpe.backbones.descriptor.data_path`)."""
    return Path(__file__).resolve().parent / "data" / PROJECTION_FILE


def fit_projection(X: np.ndarray, k: int = 384, random_dims: int = 512, pq_m: int = 448, seed: int = 0) -> Projection:
    """Principal directions of ``X [n, D]`` development descriptors, then the PQ codebook of the projections.

    The directions are those of the second moment (no mean removed), so the cosine of
    two projections approximates the descriptors' own cosine (the gate's score) rather
    than that of their deviations from a development mean. ``k`` is capped at ``n - 1``
    and ``D``. ``k + random_dims`` must be a multiple of ``pq_m``.
    """
    import faiss

    X = np.asarray(X, np.float64)
    X = X[np.any(X != 0, axis=1)]
    n, D = X.shape
    if n < 256:
        raise CompressError(f"fit_projection: {n} non-zero descriptors; the product quantiser's 256 centroids "
                            f"need at least 256")
    k = int(min(k, n - 1, D))
    # eigen-decomposition of the n x n Gram matrix (n << D): the right singular vectors
    w, U = np.linalg.eigh(X @ X.T)
    order = np.argsort(w)[::-1][:k]
    w, U = np.maximum(w[order], 1e-12), U[:, order]
    comps = (U.T @ X) / np.sqrt(w)[:, None]
    comps /= np.linalg.norm(comps, axis=1, keepdims=True)
    dims, pq_m = k + int(random_dims), int(pq_m)
    if pq_m < 1 or dims % pq_m:
        raise CompressError(f"fit_projection: {dims} projected values do not split into pq_m = {pq_m} sub-vectors")
    proto = Projection(comps.astype(np.float32), int(random_dims), int(seed),
                       np.zeros((pq_m, 256, dims // pq_m), np.float32))
    Y = proto.project(X.astype(np.float32))
    pq = faiss.ProductQuantizer(int(dims), int(pq_m), 8)
    pq.cp.seed = int(seed)
    pq.cp.min_points_per_centroid = 1  # development sets are small: fewer than 39 points per centroid is fine
    pq.cp.max_points_per_centroid = 10_000
    pq.train(np.ascontiguousarray(Y, np.float32))
    cents = faiss.vector_to_array(pq.centroids).reshape(pq_m, 256, dims // pq_m).astype(np.float32)
    return Projection(proto.components, proto.random_dims, proto.random_seed, cents)


def save_projection(proj: Projection, path: str | Path, **meta: Any) -> Path:
    """Write ``proj`` atomically as ``.npz`` (components as int8 with one float32 scale per row, the
    PQ centroids as float16: a quarter / half the size; the codebook id is that of the file as
    reloaded) with ``meta`` (provenance) as JSON."""
    path = Path(path)
    scale = np.maximum(np.abs(proj.components).max(axis=1), 1e-30).astype(np.float32) / 127.0
    q = np.clip(np.round(proj.components / scale[:, None]), -127, 127).astype(np.int8)
    atomic_write_npz(path, components_int8=q, components_scale=scale, random_dims=np.int64(proj.random_dims),
             random_seed=np.int64(proj.random_seed), pq_centroids=proj.pq_centroids.astype(np.float16),
             thresholds=np.array(json.dumps(proj.thresholds)), meta=np.array(json.dumps({**proj.meta, **meta})))
    return path


def load_projection(path: str | Path | None = None) -> Projection:
    """Read a projection file (None: the shipped one); every field checked, errors name the file."""
    path = Path(path) if path else default_projection_path()
    if not path.is_file():
        raise CompressError(f"descriptor projection: file not found: {path} "
                            f"(run `cerpe fit projection` to create it)")
    try:
        with np.load(path) as z:
            data = {k: z[k] for k in z.files}
        C = data["components_int8"].astype(np.float32) * np.asarray(data["components_scale"], np.float32)[:, None]
        P = np.asarray(data["pq_centroids"], np.float32)
        kr, seed = int(data["random_dims"]), int(data["random_seed"])
        th, meta = json.loads(str(data["thresholds"])), json.loads(str(data["meta"]))
    except Exception as exc:
        raise CompressError(f"descriptor projection: cannot read {path} (truncated, corrupt or a field "
                            f"missing?): {type(exc).__name__}: {exc}") from None
    ok = (C.ndim == 2 and P.ndim == 3 and P.shape[1] == 256 and kr >= 0 and seed >= 0
          and P.shape[0] * P.shape[2] == C.shape[0] + kr and np.all(np.isfinite(C)) and np.all(np.isfinite(P)))
    if not ok:
        raise CompressError(f"descriptor projection: {path}: inconsistent fields: components {C.shape}, "
                            f"random_dims {kr}, random_seed {seed}, pq_centroids {P.shape}")
    return Projection(C, kr, seed, P, th, meta)


@lru_cache(maxsize=8)
def _cached_projection(path: str) -> Projection:
    return load_projection(path or None)


class DescriptorCodec:
    """One compressed descriptor codec (``pca-int8`` or ``pca-pq``) over a :class:`Projection`."""

    def __init__(self, name: str, projection: Projection) -> None:
        if name not in CODECS:
            raise CompressError(f"descriptor codec must be one of {list(CODECS)}, got {name!r}")
        self.name, self.projection = name, projection
        self.codebook = projection.codebook
        self.dims = projection.dims
        self.code_bytes = 4 + self.dims if name == "pca-int8" else projection.pq_m

    @property
    def tau(self) -> float | None:
        """The gate threshold calibrated for this codec's scores (None: not calibrated)."""
        v = self.projection.thresholds.get(self.name, {}).get("tau")
        return None if v is None else float(v)

    def wire_bytes(self) -> int:
        """Exact size of one descriptor frame of this codec."""
        return DescriptorMessage.wire_bytes(self.code_bytes, self.name)

    def quantise(self, d: np.ndarray) -> np.ndarray:
        """``[D]`` descriptor -> ``[code_bytes] uint8`` code (empty for the zero descriptor)."""
        d = np.asarray(d, np.float32).ravel()
        if d.size != self.projection.dim or not np.all(np.isfinite(d)):
            raise CompressError(f"{self.name}: descriptor of {d.size} values (finite: {bool(np.all(np.isfinite(d)))})"
                                f", the projection takes {self.projection.dim}")
        if not np.any(d):
            return np.zeros(0, np.uint8)
        y = self.projection.project(d)
        if self.name == "pca-int8":
            scale = float(np.max(np.abs(y))) / 127.0 or 1.0
            q = np.clip(np.round(y / scale), -127, 127).astype(np.int8)
            return np.frombuffer(struct.pack("<f", scale) + q.tobytes(), np.uint8).copy()
        P = self.projection.pq_centroids  # [M, 256, s]
        sub = y.reshape(P.shape[0], 1, P.shape[2])
        return np.argmin(np.sum((P - sub) ** 2, axis=2), axis=1).astype(np.uint8)

    def dequantise(self, code: np.ndarray) -> np.ndarray:
        """``[code_bytes] uint8`` -> ``[dims] float32`` (zeros for the empty code); raises
        :class:`CompressError` on a code that does not decode."""
        code = np.asarray(code, np.uint8).ravel()
        if code.size == 0:
            return np.zeros(self.dims, np.float32)
        if code.size != self.code_bytes:
            raise CompressError(f"{self.name}: code of {code.size} bytes, expected {self.code_bytes}")
        if self.name == "pca-int8":
            (scale,) = struct.unpack("<f", code[:4].tobytes())
            if not (np.isfinite(scale) and scale > 0):
                raise CompressError(f"{self.name}: scale {scale} is not a positive number")
            return code[4:].view(np.int8).astype(np.float32) * np.float32(scale)
        P = self.projection.pq_centroids
        return P[np.arange(P.shape[0]), code.astype(np.intp)].reshape(-1).astype(np.float32)

    def wire(self, d: np.ndarray) -> np.ndarray:
        """The values a receiver scores for ``d``: ``dequantise(quantise(d))``."""
        return self.dequantise(self.quantise(d))

    def message(self, sender: int, step: int, d: np.ndarray) -> DescriptorMessage:
        return DescriptorMessage(sender, step, self.quantise(d), self.name, self.codebook)

    def decode(self, msg: DescriptorMessage) -> tuple[np.ndarray | None, str]:
        """A received message -> ``(values, "")`` or ``(None, fault)`` (never raises; see the module docstring)."""
        if msg.dtype != self.name:
            return None, "codec-mismatch"
        if int(msg.codebook) != self.codebook:
            return None, "codebook-mismatch"
        try:
            v = self.dequantise(msg.descriptor)
        except CompressError:
            return None, "bad-code"
        if not np.all(np.isfinite(v)):
            return None, "bad-code"
        return v, ""


def make_codec(name: str, projection: str | Path | None = None) -> DescriptorCodec | None:
    """The codec ``name`` over the projection file ``projection`` (None: the shipped file), or None
    for ``full`` (the uncompressed message at ``descriptor_dtype``). Files are read once per path."""
    if name == "full":
        return None
    if name not in CODECS:
        raise CompressError(f"descriptor codec must be one of {['full', *CODECS]}, got {name!r}")
    return DescriptorCodec(name, _cached_projection(str(projection or "")))
