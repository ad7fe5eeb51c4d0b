"""Shared pieces of the per-pair baselines: error, result type, protocol, two-view geometry."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from ..errors import CerpeError
from ..geometry import make_se3
from ..scene import CameraIntrinsics


class BaselineError(CerpeError, ValueError):
    """Malformed input to a baseline, missing weight files, unknown baseline name."""


@dataclass
class PairEstimate:
    """One baseline's answer for one image pair.

    Attributes:
        T_cj_ci: ``[4,4]`` estimate of the paper's ``T_ij`` (maps points of camera i
            into camera j) with a unit-norm translation (direction only), or None.
        reason: why there is no estimate (a token of :data:`cerpe.reasons.REASONS`: ``too-few-matches``...);
            ``""`` otherwise.
        n_matches: tentative correspondences fed to RANSAC.
        n_inliers: RANSAC inliers that also pass the cheirality check.
        timings_s: stage name -> seconds.
    """

    T_cj_ci: np.ndarray | None
    reason: str = ""
    n_matches: int = 0
    n_inliers: int = 0
    timings_s: dict[str, float] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.T_cj_ci is not None


class PairBaseline(Protocol):
    name: str
    conf: dict[str, Any]

    def estimate(self, image_i: np.ndarray, K_i: CameraIntrinsics,
                 image_j: np.ndarray, K_j: CameraIntrinsics) -> PairEstimate: ...


def relative_pose_from_matches(
    pts_i_px: np.ndarray,
    pts_j_px: np.ndarray,
    K_i: CameraIntrinsics,
    K_j: CameraIntrinsics,
    *,
    min_matches: int,
    min_inliers: int,
    ransac_px: float,
    confidence: float = 0.9999,
    seed: int = 0,
) -> PairEstimate:
    """Essential-matrix RANSAC + cheirality on matched pixels of two calibrated cameras.

    The two cameras may differ, so points are normalised with their own ``K``
    first and RANSAC runs on the normalised plane; the pixel threshold is
    converted with the mean focal length of both cameras.

    Args:
        pts_i_px, pts_j_px: ``[M,2]`` matched pixel coordinates in image i and j.

    Returns:
        :class:`PairEstimate` with ``T_cj_ci`` (``x_j = R x_i + t``, ``||t|| = 1``)
        or no estimate and a reason (too few matches / inliers, degenerate E).
    """
    import cv2

    pts_i = np.asarray(pts_i_px, np.float64).reshape(-1, 2)
    pts_j = np.asarray(pts_j_px, np.float64).reshape(-1, 2)
    if pts_i.shape != pts_j.shape:
        raise BaselineError(f"matched point arrays differ in shape: {pts_i.shape} vs {pts_j.shape}")
    m = len(pts_i)
    if m < max(min_matches, 5):
        return PairEstimate(None, "too-few-matches", n_matches=m)
    n_i = cv2.undistortPoints(pts_i[:, None, :], K_i.K, None).reshape(-1, 2)
    n_j = cv2.undistortPoints(pts_j[:, None, :], K_j.K, None).reshape(-1, 2)
    f_mean = 0.25 * (K_i.fx + K_i.fy + K_j.fx + K_j.fy)
    cv2.setRNGSeed(seed)
    E, mask = cv2.findEssentialMat(n_i, n_j, np.eye(3), method=cv2.RANSAC, prob=confidence,
                                   threshold=ransac_px / f_mean)
    if E is None or E.shape[0] < 3:
        return PairEstimate(None, "essential-matrix-failed", n_matches=m)
    # findEssentialMat may stack several solutions; keep the first (best support)
    E = E[:3]
    n_inl, R, t, mask_pose = cv2.recoverPose(E, n_i, n_j, np.eye(3), mask=mask.copy())
    n_inl = int(n_inl)
    if n_inl < min_inliers:
        return PairEstimate(None, "too-few-inliers", n_matches=m, n_inliers=n_inl)
    t = np.asarray(t, np.float64).ravel()
    nt = np.linalg.norm(t)
    if not np.isfinite(nt) or nt < 1e-12 or not np.all(np.isfinite(R)):
        return PairEstimate(None, "degenerate-pose", n_matches=m, n_inliers=n_inl)
    return PairEstimate(make_se3(R, t / nt), "", n_matches=m, n_inliers=n_inl)

