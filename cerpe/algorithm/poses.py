"""The pose arithmetic of Algorithm 1: ego-motion through a view of the pass, direct estimates."""
from __future__ import annotations

import numpy as np

from ..geometry import scale_translation, se3_inverse
from .config import AlgorithmError


def check_pose(T: np.ndarray, name: str) -> np.ndarray:
    """``T`` as a finite ``[4,4]`` float64 array, or :class:`AlgorithmError` naming ``name``."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise AlgorithmError(f"{name}: expected a 4x4 pose, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise AlgorithmError(f"{name}: pose contains NaN or inf")
    return T


def _scale(s: float) -> float:
    if not (np.isfinite(s) and s > 0):
        raise AlgorithmError(f"scale must be finite and > 0, got {s}")
    return float(s)


def ego_motion(X_kf: np.ndarray, T_frame_kf: np.ndarray, T_frame_cur: np.ndarray, s: float) -> np.ndarray:
    """Metric odometry pose of the current frame through a view of the same pass.

    ``X_cur = X_kf @ scale_translation(inv(T_frame_kf) @ T_frame_cur, s)``: the
    view-to-current motion measured inside one pass (independent of that pass's
    frame), made metric by ``s``, appended to the view's stored pose.
    """
    X_kf = check_pose(X_kf, "X_kf")
    T_kf_cur = se3_inverse(check_pose(T_frame_kf, "T_frame_kf")) @ check_pose(T_frame_cur, "T_frame_cur")
    return X_kf @ scale_translation(T_kf_cur, _scale(s))


def direct_relative(T_frame_ci: np.ndarray, T_frame_cj: np.ndarray, s: float) -> np.ndarray:
    """Direct estimate ``T_cj_ci = scale_translation(inv(T_frame_cj) @ T_frame_ci, s)``."""
    T = se3_inverse(check_pose(T_frame_cj, "T_frame_cj")) @ check_pose(T_frame_ci, "T_frame_ci")
    return scale_translation(T, _scale(s))


def registered_relative(T_via_cj: np.ndarray, T_via_ci: np.ndarray, s: float) -> np.ndarray:
    """Direct estimate through one own view ``via``: ``T_cj_ci = inv(scaled(T_via_cj, s)) @ T_via_ci``.

    ``T_via_cj`` is the collaborator's registration against ``via`` in the pass's
    unit (made metric by ``s``); ``T_via_ci`` the current camera in ``via``'s, metric.
    """
    T_via_cj = scale_translation(check_pose(T_via_cj, "T_via_cj"), _scale(s))
    return se3_inverse(T_via_cj) @ check_pose(T_via_ci, "T_via_ci")
