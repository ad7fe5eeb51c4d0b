"""Pure, typed numpy geometry: SE(3), Sim(3), quaternions, the paper's errors.

Conventions (one place for all of them; see also ``docs/algorithm.md``):

* A transform ``T_a_b`` is a 4x4 homogeneous matrix that maps points expressed in
  frame ``b`` into frame ``a`` (``p_a = T_a_b @ p_b``); equivalently it is the pose
  of frame ``b`` seen from frame ``a``. Composition chains the inner names:
  ``T_a_c = T_a_b @ T_b_c``.
* Camera axes are OpenCV's (x right, y down, z forward).
* Quaternions are unit quaternions. Two layouts exist in the wild and both are
  named explicitly here: ``xyzw`` (scalar last: TUM, VGGT, scipy) and ``wxyz``
  (scalar first: nuScenes, EuRoC, roma's ``unitquat`` is xyzw).
* The paper writes ``X_i^t`` for robot ``i``'s camera-to-world odometry pose,
  i.e. ``T_odom_cam`` here, and ``T_ij = X_j^-1 X_i``, the transform that maps
  points from camera ``i`` into camera ``j`` -- in code ``T_cj_ci``. The only
  conversion between the two notations lives in :func:`paper_T_ij` and
  :func:`propagate_relative_pose`.

Every function accepts a single transform ``[4, 4]`` or a batch ``[..., 4, 4]``
unless stated otherwise. Invalid input raises :class:`GeometryError`.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import CerpeError

Array = NDArray[np.float64]


class GeometryError(CerpeError, ValueError):
    """Raised for malformed or non-finite geometric input."""


# --------------------------------------------------------------------------- checks
def _as_transform(T: ArrayLike, name: str = "T") -> Array:
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] != (4, 4):
        raise GeometryError(f"{name}: expected shape [...,4,4], got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise GeometryError(f"{name}: contains NaN or inf")
    return T


def is_finite_transform(T: ArrayLike) -> bool:
    """True when ``T`` is a finite 4x4 matrix (no validity check of the rotation)."""
    T = np.asarray(T)
    return T.shape[-2:] == (4, 4) and bool(np.all(np.isfinite(T)))


def check_se3(T: ArrayLike, name: str = "T", atol: float = 1e-5) -> Array:
    """Return ``T`` as float64 after checking it is a proper rigid transform.

    Raises :class:`GeometryError` naming ``name`` when it is not finite, its
    rotation block is not orthonormal with determinant +1, or its last row is
    not ``[0, 0, 0, 1]``.
    """
    T = _as_transform(T, name)
    R = T[..., :3, :3]
    eye = np.broadcast_to(np.eye(3), R.shape)
    if not np.allclose(R @ np.swapaxes(R, -1, -2), eye, atol=atol):
        raise GeometryError(f"{name}: rotation block is not orthonormal")
    if not np.allclose(np.linalg.det(R), 1.0, atol=atol):
        raise GeometryError(f"{name}: rotation block has determinant != +1")
    if not np.allclose(T[..., 3, :], [0.0, 0.0, 0.0, 1.0], atol=atol):
        raise GeometryError(f"{name}: last row is not [0, 0, 0, 1]")
    return T


# --------------------------------------------------------------------------- SE(3)
def make_se3(R: ArrayLike, t: ArrayLike) -> Array:
    """Build ``[...,4,4]`` from rotation ``[...,3,3]`` and translation ``[...,3]``."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if R.shape[-2:] != (3, 3) or t.shape[-1] != 3:
        raise GeometryError(f"make_se3: bad shapes R{R.shape} t{t.shape}")
    batch = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = np.zeros(batch + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def se3_inverse(T: ArrayLike) -> Array:
    """Closed-form inverse of a rigid transform: ``T_b_a`` from ``T_a_b``."""
    T = _as_transform(T)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Rt = np.swapaxes(R, -1, -2)
    return make_se3(Rt, -np.einsum("...ij,...j->...i", Rt, t))


def compose(*Ts: ArrayLike) -> Array:
    """Left-to-right matrix product ``T1 @ T2 @ ...`` with checks."""
    if not Ts:
        raise GeometryError("compose: needs at least one transform")
    out = _as_transform(Ts[0], "T0")
    for k, T in enumerate(Ts[1:], start=1):
        out = out @ _as_transform(T, f"T{k}")
    return out


def transform_points(T_a_b: ArrayLike, p_b: ArrayLike) -> Array:
    """Map points ``[..., N, 3]`` from frame b into frame a."""
    T = _as_transform(T_a_b, "T_a_b")
    p = np.asarray(p_b, dtype=np.float64)
    return np.einsum("...ij,...nj->...ni", T[..., :3, :3], p) + T[..., None, :3, 3]


def compose_increments(T_w_c0: ArrayLike, T_prev_cur: ArrayLike) -> Array:
    """Chain relative motions into absolute poses without interpolation.

    Args:
        T_w_c0: ``[4,4]`` pose of the first camera.
        T_prev_cur: ``[N,4,4]`` increments, ``T_prev_cur[k] = T_{c_k}_{c_{k+1}}``.

    Returns:
        ``[N+1,4,4]`` poses ``T_w_ck``; the first is ``T_w_c0``.
    """
    T0 = _as_transform(T_w_c0, "T_w_c0")
    incs = _as_transform(T_prev_cur, "T_prev_cur").reshape(-1, 4, 4)
    out = np.empty((len(incs) + 1, 4, 4))
    out[0] = T0
    for k, inc in enumerate(incs):
        out[k + 1] = out[k] @ inc
    return out


def relative_increments(T_w_c: ArrayLike) -> Array:
    """Inverse of :func:`compose_increments`: ``[N,4,4]`` -> ``[N-1,4,4]``."""
    T = _as_transform(T_w_c, "T_w_c")
    return se3_inverse(T[:-1]) @ T[1:]


# --------------------------------------------------------------------------- Sim(3)
def make_sim3(s: float, R: ArrayLike, t: ArrayLike) -> Array:
    """``[4,4]`` similarity ``[[s R, t], [0, 1]]``; ``s`` must be finite and > 0."""
    if not (np.isfinite(s) and s > 0):
        raise GeometryError(f"make_sim3: scale must be finite and > 0, got {s}")
    S = make_se3(R, t)
    S[..., :3, :3] *= s
    return S


def sim3_inverse(S: ArrayLike) -> Array:
    """Inverse of a similarity ``[[sR, t], [0, 1]]``."""
    S = _as_transform(S, "S")
    sR = S[..., :3, :3]
    s = np.cbrt(np.linalg.det(sR))
    if np.any(s <= 0):
        raise GeometryError("sim3_inverse: non-positive scale")
    R = sR / s[..., None, None]
    Rt = np.swapaxes(R, -1, -2)
    out = make_se3(Rt / s[..., None, None], -np.einsum("...ij,...j->...i", Rt, S[..., :3, 3]) / s[..., None])
    return out


def scale_translation(T: ArrayLike, s: float) -> Array:
    """Apply the paper's ``S = diag(s, s, s, 1)`` to the translation of a rigid transform.

    This is how an up-to-scale backbone pose becomes metric: the rotation is
    scale-free, the translation is multiplied by ``s``.
    """
    if not (np.isfinite(s) and s > 0):
        raise GeometryError(f"scale_translation: scale must be finite and > 0, got {s}")
    T = _as_transform(T).copy()
    T[..., :3, 3] *= s
    return T


# --------------------------------------------------------------------------- rotations
def skew(v: ArrayLike) -> Array:
    v = np.asarray(v, dtype=np.float64)
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], z, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


def so3_exp(omega: ArrayLike) -> Array:
    """Rodrigues: axis-angle ``[...,3]`` (radians) -> rotation ``[...,3,3]``."""
    w = np.asarray(omega, dtype=np.float64)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = theta < 1e-8
    th = np.where(small, 1.0, theta)
    A = np.where(small, 1.0 - theta**2 / 6.0, np.sin(th) / th)
    B = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(th)) / th**2)
    return np.eye(3) + A * K + B * (K @ K)


def rotation_angle(R: ArrayLike) -> Array:
    """Geodesic angle (radians) of rotation matrices ``[...,3,3]``."""
    R = np.asarray(R, dtype=np.float64)
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(c, -1.0, 1.0))


def quat_xyzw_to_matrix(q_xyzw: ArrayLike) -> Array:
    """Unit quaternion, scalar LAST ``[...,4]`` -> rotation ``[...,3,3]``.

    The quaternion is normalised; a zero or non-finite quaternion raises.
    """
    q = np.asarray(q_xyzw, dtype=np.float64)
    if q.shape[-1] != 4:
        raise GeometryError(f"quaternion: expected [...,4], got {q.shape}")
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if not np.all(np.isfinite(q)) or np.any(n < 1e-9):
        raise GeometryError("quaternion: zero-norm or non-finite quaternion")
    x, y, z, w = np.moveaxis(q / n, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def quat_wxyz_to_matrix(q_wxyz: ArrayLike) -> Array:
    """Unit quaternion, scalar FIRST ``[...,4]`` -> rotation ``[...,3,3]``."""
    return quat_xyzw_to_matrix(wxyz_to_xyzw(q_wxyz))


def matrix_to_quat_xyzw(R: ArrayLike) -> Array:
    """Rotation ``[...,3,3]`` -> unit quaternion scalar LAST with ``w >= 0``."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] != (3, 3):
        raise GeometryError(f"rotation: expected [...,3,3], got {R.shape}")
    m = R.reshape(-1, 3, 3)
    q = np.empty((len(m), 4))
    for k, M in enumerate(m):
        tr = np.trace(M)
        if tr > 0:
            S = np.sqrt(tr + 1.0) * 2
            q[k] = [(M[2, 1] - M[1, 2]) / S, (M[0, 2] - M[2, 0]) / S, (M[1, 0] - M[0, 1]) / S, 0.25 * S]
        elif M[0, 0] > M[1, 1] and M[0, 0] > M[2, 2]:
            S = np.sqrt(1.0 + M[0, 0] - M[1, 1] - M[2, 2]) * 2
            q[k] = [0.25 * S, (M[0, 1] + M[1, 0]) / S, (M[0, 2] + M[2, 0]) / S, (M[2, 1] - M[1, 2]) / S]
        elif M[1, 1] > M[2, 2]:
            S = np.sqrt(1.0 + M[1, 1] - M[0, 0] - M[2, 2]) * 2
            q[k] = [(M[0, 1] + M[1, 0]) / S, 0.25 * S, (M[1, 2] + M[2, 1]) / S, (M[0, 2] - M[2, 0]) / S]
        else:
            S = np.sqrt(1.0 + M[2, 2] - M[0, 0] - M[1, 1]) * 2
            q[k] = [(M[0, 2] + M[2, 0]) / S, (M[1, 2] + M[2, 1]) / S, 0.25 * S, (M[1, 0] - M[0, 1]) / S]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q[q[:, 3] < 0] *= -1.0
    return q.reshape(R.shape[:-2] + (4,))


def matrix_to_quat_wxyz(R: ArrayLike) -> Array:
    """Rotation ``[...,3,3]`` -> unit quaternion scalar FIRST with ``w >= 0``."""
    return xyzw_to_wxyz(matrix_to_quat_xyzw(R))


def xyzw_to_wxyz(q: ArrayLike) -> Array:
    q = np.asarray(q, dtype=np.float64)
    return np.concatenate([q[..., 3:4], q[..., 0:3]], axis=-1)


def wxyz_to_xyzw(q: ArrayLike) -> Array:
    q = np.asarray(q, dtype=np.float64)
    return np.concatenate([q[..., 1:4], q[..., 0:1]], axis=-1)


def se3_from_tq_xyzw(t: ArrayLike, q_xyzw: ArrayLike) -> Array:
    """Pose from translation ``[...,3]`` and scalar-last quaternion (TUM layout)."""
    return make_se3(quat_xyzw_to_matrix(q_xyzw), t)


def se3_to_tq_xyzw(T: ArrayLike) -> tuple[Array, Array]:
    """Pose -> (translation ``[...,3]``, scalar-last quaternion ``[...,4]``)."""
    T = _as_transform(T)
    return T[..., :3, 3].copy(), matrix_to_quat_xyzw(T[..., :3, :3])


def slerp_xyzw(q0: ArrayLike, q1: ArrayLike, alpha: float) -> Array:
    """Spherical linear interpolation between two scalar-last unit quaternions."""
    q0 = np.asarray(q0, dtype=np.float64) / np.linalg.norm(q0)
    q1 = np.asarray(q1, dtype=np.float64) / np.linalg.norm(q1)
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + alpha * (q1 - q0)
        return q / np.linalg.norm(q)
    th = np.arccos(d)
    return (np.sin((1 - alpha) * th) * q0 + np.sin(alpha * th) * q1) / np.sin(th)


def interpolate_pose(T0: ArrayLike, T1: ArrayLike, alpha: float) -> Array:
    """Pose between ``T0`` (alpha=0) and ``T1`` (alpha=1): SLERP rotation, linear translation."""
    t0, q0 = se3_to_tq_xyzw(T0)
    t1, q1 = se3_to_tq_xyzw(T1)
    return se3_from_tq_xyzw((1 - alpha) * t0 + alpha * t1, slerp_xyzw(q0, q1, alpha))


def random_se3(rng: np.random.Generator, max_translation: float = 10.0) -> Array:
    """A uniformly random rotation and a translation in a cube; for tests and tools."""
    q = rng.normal(size=4)
    return se3_from_tq_xyzw(rng.uniform(-max_translation, max_translation, 3), q)


# --------------------------------------------------------------------------- paper notation
def paper_T_ij(X_i: ArrayLike, X_j: ArrayLike) -> Array:
    """The paper's ``T_ij = X_j^-1 X_i`` -- in code ``T_cj_ci``.

    Args:
        X_i: ``T_w_ci``, camera-to-world pose of robot i's camera.
        X_j: ``T_w_cj``, camera-to-world pose of robot j's camera, same world.

    Returns:
        ``T_cj_ci``: maps points in camera i into camera j (pose of i seen from j).
    """
    return se3_inverse(X_j) @ _as_transform(X_i, "X_i")


def propagate_relative_pose(
    T_cj_ci_anchor: ArrayLike,
    X_i_anchor: ArrayLike,
    X_i_now: ArrayLike,
    X_j_anchor: ArrayLike,
    X_j_now: ArrayLike,
) -> Array:
    """Propagate an anchor with both robots' ego-motion (paper Eq. propagation).

    ``T_ij^t = (X_j^t)^-1 X_j^(t-k) T_ij^(t-k) (X_i^(t-k))^-1 X_i^t``, where each
    ``X`` is that robot's *own* odometry pose ``T_odom_cam`` (the two robots'
    odometry frames are unrelated; only differences within one robot are used).
    """
    return compose(
        se3_inverse(X_j_now), X_j_anchor, T_cj_ci_anchor, se3_inverse(X_i_anchor), X_i_now
    )


# --------------------------------------------------------------------------- pose covariances
# A pose covariance here is ``[6,6]`` over the tangent ``xi = [omega, v]`` (rotation first, as
# GTSAM orders it) of a right perturbation. The true pose is ``T @ exp(xi)``, i.e. the error
# is expressed in the frame of the pose's own camera (``ci`` for ``T_cj_ci``).
def se3_adjoint(T: ArrayLike) -> Array:
    """``[...,6,6]`` adjoint of ``T`` in the ``[omega, v]`` order: ``T exp(xi) T^-1 = exp(Ad_T xi)``."""
    T = _as_transform(T)
    R, t = T[..., :3, :3], T[..., :3, 3]
    A = np.zeros(T.shape[:-2] + (6, 6))
    A[..., :3, :3] = R
    A[..., 3:, 3:] = R
    A[..., 3:, :3] = skew(t) @ R
    return A


def pose_cov_sigmas(cov: ArrayLike) -> tuple[Array, Array]:
    """``(sigma_pos_m, sigma_rot_rad)`` of ``[...,6,6]`` covariances: the predicted RMS errors.

    ``sqrt(trace)`` of the translation and rotation blocks: the expected value of
    ``e_pos**2`` and (to first order) ``e_rot**2`` under the covariance; NaN where
    the covariance is not finite.
    """
    C = np.asarray(cov, dtype=np.float64)
    if C.shape[-2:] != (6, 6):
        raise GeometryError(f"pose covariance: expected shape [...,6,6], got {C.shape}")
    rot = np.sqrt(np.clip(np.trace(C[..., :3, :3], axis1=-2, axis2=-1), 0, None))
    pos = np.sqrt(np.clip(np.trace(C[..., 3:, 3:], axis1=-2, axis2=-1), 0, None))
    return pos, rot


def pose_cov_in_parent(T: ArrayLike, cov: ArrayLike) -> Array:
    """A right-perturbation covariance of ``T_a_b`` as ROS ``PoseWithCovariance`` orders it.

    Returns ``[...,6,6]`` over ``(x, y, z, rot_x, rot_y, rot_z)``: the position error and
    the rotation error (about fixed axes), both expressed in frame ``a`` (the pose's
    parent, ``header.frame_id``). First order: ``dt = R v``, ``dtheta = R omega``.
    """
    T = _as_transform(T)
    C = np.asarray(cov, dtype=np.float64)
    R = T[..., :3, :3]
    M = np.zeros(T.shape[:-2] + (6, 6))
    M[..., :3, 3:] = R
    M[..., 3:, :3] = R
    return M @ C @ np.swapaxes(M, -1, -2)


# --------------------------------------------------------------------------- errors (paper IV)
def e_pos(t_est: ArrayLike, t_gt: ArrayLike) -> Array:
    """``||t_hat - t||_2`` in metres, over the last axis."""
    return np.linalg.norm(np.asarray(t_est, float) - np.asarray(t_gt, float), axis=-1)


def e_rot_quat(q_est: ArrayLike, q_gt: ArrayLike) -> Array:
    """``4 arcsin(0.5 min(||q_hat - q||, ||q_hat + q||))`` in radians (geodesic angle).

    Works for either quaternion layout as long as both use the same one.
    """
    q1 = np.asarray(q_est, float)
    q2 = np.asarray(q_gt, float)
    q1 = q1 / np.linalg.norm(q1, axis=-1, keepdims=True)
    q2 = q2 / np.linalg.norm(q2, axis=-1, keepdims=True)
    d = np.minimum(np.linalg.norm(q1 - q2, axis=-1), np.linalg.norm(q1 + q2, axis=-1))
    return 4.0 * np.arcsin(np.clip(0.5 * d, 0.0, 1.0))


def e_rot(T_est: ArrayLike, T_gt: ArrayLike) -> Array:
    """Rotation error of two poses ``[...,4,4]``, via :func:`e_rot_quat` (radians)."""
    return e_rot_quat(
        matrix_to_quat_xyzw(_as_transform(T_est)[..., :3, :3]),
        matrix_to_quat_xyzw(_as_transform(T_gt)[..., :3, :3]),
    )


def gt_scale_translation(t_est: ArrayLike, t_gt: ArrayLike) -> Array:
    """Rescale the estimate to the ground-truth norm: ``t_hat * ||t|| / ||t_hat||``.

    A zero estimate stays zero (there is no direction to rescale).
    """
    t_est = np.asarray(t_est, float)
    t_gt = np.asarray(t_gt, float)
    n_est = np.linalg.norm(t_est, axis=-1, keepdims=True)
    n_gt = np.linalg.norm(t_gt, axis=-1, keepdims=True)
    safe = np.where(n_est > 1e-12, n_est, 1.0)
    return np.where(n_est > 1e-12, t_est * n_gt / safe, 0.0)


def viewing_angle(T_cj_ci: ArrayLike) -> Array:
    """Relative viewing angle (radians) between two cameras: rotation angle of ``T_cj_ci``."""
    return rotation_angle(_as_transform(T_cj_ci)[..., :3, :3])
