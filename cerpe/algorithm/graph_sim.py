"""A simulated measurement stream for one ordered pair: what :class:`~cerpe.algorithm.graph.PairGraph`
consumes, with known ground truth. For tests and for timing the graph alone (``cerpe bench``);
no image is involved, so a 60 s encounter at 10 Hz costs milliseconds to make.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import make_se3, se3_inverse, so3_exp


@dataclass
class PairStream:
    """Ground truth and measurements of one pair over ``T`` steps.

    ``G_i``, ``G_j``: ``[T,4,4]`` true camera poses in one world; ``X_i``, ``X_j``: the
    odometry poses each robot reports (identity at step 0, drifting with the noise);
    ``direct``: step -> measured ``T_cj_ci``; ``truth``: ``[T,4,4]`` true ``T_cj_ci``.
    """

    G_i: np.ndarray
    G_j: np.ndarray
    X_i: np.ndarray
    X_j: np.ndarray
    direct: dict[int, np.ndarray]
    truth: np.ndarray


def _trajectory(rng: np.random.Generator, T: int, speed: float, start: np.ndarray) -> np.ndarray:
    """A smooth ground-vehicle-like path: forward motion with a slowly varying yaw rate."""
    G = np.zeros((T, 4, 4))
    G[0] = start
    yaw_rate = 0.0
    for t in range(1, T):
        yaw_rate = 0.9 * yaw_rate + 0.1 * rng.normal(0, 0.05)
        step = make_se3(so3_exp(np.array([0.0, yaw_rate, 0.0])), np.array([0.0, 0.0, speed]))
        G[t] = G[t - 1] @ step
    return G


def _odometry(rng: np.random.Generator, G: np.ndarray, rot_sigma: float, trans_sigma: float) -> np.ndarray:
    X = np.zeros_like(G)
    X[0] = np.eye(4)
    for t in range(1, len(G)):
        D = se3_inverse(G[t - 1]) @ G[t]
        noise = make_se3(so3_exp(rng.normal(0, rot_sigma, 3)), rng.normal(0, trans_sigma, 3)) \
            if rot_sigma > 0 or trans_sigma > 0 else np.eye(4)
        X[t] = X[t - 1] @ D @ noise
    return X


def perturb(rng: np.random.Generator, T: np.ndarray, rot_sigma: float, trans_sigma: float) -> np.ndarray:
    """``T @ exp([omega, v])`` with ``omega ~ N(0, rot_sigma^2)``, ``v ~ N(0, trans_sigma^2)`` per axis."""
    return T @ make_se3(so3_exp(rng.normal(0, rot_sigma, 3)), rng.normal(0, trans_sigma, 3))


def simulate_pair(seed: int = 0, n_steps: int = 60, speed_m: float = 0.1, odo_rot: float = 0.0,
                  odo_trans: float = 0.0, direct_every: int = 5, direct_rot: float = 0.0,
                  direct_trans: float = 0.0, direct_steps: list[int] | None = None) -> PairStream:
    """Two robots driving near each other; direct estimates every ``direct_every`` steps (or at
    ``direct_steps``) with Gaussian noise of the given standard deviations (radians, metres)."""
    rng = np.random.default_rng(seed)
    G_i = _trajectory(rng, n_steps, speed_m, np.eye(4))
    G_j = _trajectory(rng, n_steps, speed_m, make_se3(so3_exp(np.array([0.0, 0.4, 0.0])), np.array([2.0, 0.0, 1.0])))
    X_i = _odometry(rng, G_i, odo_rot, odo_trans)
    X_j = _odometry(rng, G_j, odo_rot, odo_trans)
    truth = se3_inverse(G_j) @ G_i
    steps = direct_steps if direct_steps is not None else list(range(0, n_steps, max(int(direct_every), 1)))
    direct = {int(t): perturb(rng, truth[t], direct_rot, direct_trans) for t in steps}
    return PairStream(G_i, G_j, X_i, X_j, direct, truth)
