"""SIFT + ratio test + essential-matrix RANSAC (OpenCV), per image pair."""
from __future__ import annotations

import time
from typing import Any

import numpy as np

from ..scene import CameraIntrinsics
from .base import BaselineError, PairEstimate, relative_pose_from_matches


class SiftRansac:
    """OpenCV SIFT features, mutual-free Lowe ratio matching, 5-point RANSAC.

    ``default_conf``:
        max_features: SIFT keypoint budget per image.
        ratio: Lowe ratio test threshold (nearest / second nearest distance).
        ransac_px: RANSAC inlier threshold in pixels.
        min_matches / min_inliers: below these the pair has no estimate.
    """

    name = "sift-ransac"
    default_conf: dict[str, Any] = {
        "max_features": 4000,
        "ratio": 0.8,
        "ransac_px": 1.0,
        "min_matches": 15,
        "min_inliers": 15,
        "seed": 0,
    }

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        unknown = set(conf or {}) - set(self.default_conf)
        if unknown:
            raise BaselineError(f"sift-ransac: unknown config keys {sorted(unknown)}")
        self.conf = {**self.default_conf, **(conf or {})}
        import cv2

        self._sift = cv2.SIFT_create(nfeatures=int(self.conf["max_features"]))
        self._matcher = cv2.BFMatcher(cv2.NORM_L2)

    def _features(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        import cv2

        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise BaselineError(f"sift-ransac: expected [H,W,3] uint8 RGB, got {image.shape} {image.dtype}")
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        kps, desc = self._sift.detectAndCompute(gray, None)
        pts = np.array([k.pt for k in kps], np.float64).reshape(-1, 2)
        return pts, desc

    def estimate(self, image_i: np.ndarray, K_i: CameraIntrinsics,
                 image_j: np.ndarray, K_j: CameraIntrinsics) -> PairEstimate:
        t0 = time.perf_counter()
        p_i, d_i = self._features(image_i)
        p_j, d_j = self._features(image_j)
        t1 = time.perf_counter()
        if d_i is None or d_j is None or len(p_i) < 2 or len(p_j) < 2:
            return PairEstimate(None, "too-few-keypoints",
                                timings_s={"features": t1 - t0})
        knn = self._matcher.knnMatch(d_i, d_j, k=2)
        good = [m[0] for m in knn if len(m) == 2 and m[0].distance < self.conf["ratio"] * m[1].distance]
        mi = np.array([g.queryIdx for g in good], int)
        mj = np.array([g.trainIdx for g in good], int)
        t2 = time.perf_counter()
        est = relative_pose_from_matches(
            p_i[mi] if len(mi) else np.zeros((0, 2)), p_j[mj] if len(mj) else np.zeros((0, 2)), K_i, K_j,
            min_matches=int(self.conf["min_matches"]), min_inliers=int(self.conf["min_inliers"]),
            ransac_px=float(self.conf["ransac_px"]), seed=int(self.conf["seed"]),
        )
        est.timings_s = {"features": t1 - t0, "matching": t2 - t1, "ransac": time.perf_counter() - t2}
        return est
