"""TUM trajectory text, the one writer (``cerpe.datasets.formats.read_trajectory`` reads it).

Kept out of ``cerpe.datasets`` so that the synthetic writer, the run folders and the
dataset adapters share it without depending on each other.
"""
from __future__ import annotations

import numpy as np

from .geometry import pose_cov_in_parent, se3_to_tq_xyzw

__all__ = ["COV_HEADER", "format_tum", "format_tum_cov", "parse_tum_cov"]

COV_HEADER = ("timestamp, then the 6x6 covariance of the pose with this timestamp in the .tum file beside, "
              "row-major (36 values), in ROS PoseWithCovariance order (x y z rot_x rot_y rot_z): position and "
              "rotation (fixed axes) errors in the pose's parent frame; m^2, rad^2")


def format_tum(stamps_s: np.ndarray, T: np.ndarray,
               header: str = "timestamp tx ty tz qx qy qz qw", stamp_decimals: int = 9) -> str:
    """TUM trajectory text, ``stamp tx ty tz qx qy qz qw`` per pose ``T [N,4,4]``.

    Quaternions scalar-last; evo and :func:`read_trajectory` (``fmt="tum"``) read it unchanged.
    """
    lines = [f"# {header}"]
    for s, Tk in zip(stamps_s, T):
        t, q = se3_to_tq_xyzw(Tk)
        lines.append(f"{s:.{stamp_decimals}f} " + " ".join(f"{v:.9f}" for v in (*t, *q)))
    return "\n".join(lines) + "\n"


def format_tum_cov(stamps_s: np.ndarray, T: np.ndarray, cov: np.ndarray, stamp_decimals: int = 9) -> str:
    """The covariance companion of a TUM file: ``stamp c00 c01 ... c55`` per pose.

    ``cov [N,6,6]`` are right-perturbation covariances over ``[rotation, translation]``
    (:mod:`cerpe.geometry`, "pose covariances") of the poses ``T [N,4,4]``. Written in ROS
    ``PoseWithCovariance`` order and frame (:func:`~cerpe.geometry.pose_cov_in_parent`), so a
    line pairs with the TUM line of the same stamp as a ``PoseWithCovarianceStamped`` would.
    Unknown entries are written as ``nan``: a covariance that knows the rotation only (no metric depth:
    the translation's scale is unknown) keeps its rotation block and has ``nan`` in every row and
    column of the position.
    """
    lines = [f"# {COV_HEADER}"]
    for s, Tk, Ck in zip(stamps_s, T, cov):
        Ck = np.asarray(Ck, dtype=np.float64)
        if np.all(np.isfinite(Ck)):
            C = pose_cov_in_parent(Tk, Ck)
        elif np.all(np.isfinite(Ck[:3, :3])):  # the rotation block alone (first order: it maps on its own)
            C = pose_cov_in_parent(Tk, np.where(np.isfinite(Ck), Ck, 0.0))
            C[:3, :] = np.nan
            C[:, :3] = np.nan
        else:
            C = np.full((6, 6), np.nan)
        lines.append(f"{s:.{stamp_decimals}f} " + " ".join(f"{v:.9g}" for v in C.ravel()))
    return "\n".join(lines) + "\n"


def parse_tum_cov(text: str) -> tuple[np.ndarray, np.ndarray]:
    """``(stamps [N], cov [N,6,6])`` of :func:`format_tum_cov` text (ROS order, parent frame).

    Raises ``ValueError`` naming the line for a line without 37 numbers.
    """
    stamps, covs = [], []
    for k, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        v = line.split()
        if len(v) != 37:
            raise ValueError(f"covariance line {k}: {len(v)} values, expected 37 (stamp + 6x6)")
        stamps.append(float(v[0]))
        covs.append(np.array(v[1:], dtype=np.float64).reshape(6, 6))
    return np.array(stamps), np.array(covs).reshape(-1, 6, 6)
