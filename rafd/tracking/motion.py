"""Constant-velocity Kalman filter in the world frame, batched over tracks: state (x, y, vx, vy), metres and m/s.

Pure functions of arrays: nothing is modified in place, so a tracker state built from their outputs stays valid
after another step (rafd.tracking.state). AB3DMOT's filter, without the box size and heading in the state: a
radar box's size and yaw are what the annotator drew around a blurred return, not a motion to smooth.
"""

from __future__ import annotations

import math

import numpy as np


def inverse_2x2(matrices: np.ndarray) -> np.ndarray:
    """[N, 2, 2] symmetric positive-definite -> [N, 2, 2] inverses (closed form: no LAPACK call per matrix)."""
    a, b, d = matrices[:, 0, 0], matrices[:, 0, 1], matrices[:, 1, 1]
    determinant = a * d - b * b  # [N]
    inverse = np.empty_like(matrices)
    inverse[:, 0, 0] = d / determinant
    inverse[:, 1, 1] = a / determinant
    inverse[:, 0, 1] = inverse[:, 1, 0] = -b / determinant
    return inverse


def initial_covariance(count: int, position_std: float, velocity_var: np.ndarray) -> np.ndarray:
    """-> [N, 4, 4] a new track's covariance: its detection's position noise, velocity_var [N, 2, 2] (m/s)^2."""
    covariance = np.zeros((count, 4, 4))
    covariance[:, 0, 0] = covariance[:, 1, 1] = position_std**2
    covariance[:, 2:, 2:] = velocity_var
    return covariance


def predict(mean: np.ndarray, covariance: np.ndarray, dt: float, acceleration_std: float):
    """(mean [N, 4], covariance [N, 4, 4]) -> the same `dt` seconds later (white-noise acceleration)."""
    moved = mean.copy()
    moved[:, :2] += dt * mean[:, 2:]
    transition = np.eye(4)
    transition[0, 2] = transition[1, 3] = dt
    q = acceleration_std**2
    noise = np.zeros((4, 4))
    noise[0, 0] = noise[1, 1] = q * dt**3 / 3.0
    noise[0, 2] = noise[2, 0] = noise[1, 3] = noise[3, 1] = q * dt**2 / 2.0
    noise[2, 2] = noise[3, 3] = q * dt
    spread = transition @ covariance @ transition.T + noise  # [N, 4, 4]
    return moved, spread


def update(
    mean: np.ndarray, covariance: np.ndarray, measured: np.ndarray, noise: np.ndarray, part: slice
) -> tuple[np.ndarray, np.ndarray]:
    """One 2-D measurement per track of the state's `part` (slice(0, 2): position, slice(2, 4): velocity):
    (mean [N, 4], covariance [N, 4, 4], measured [N, 2], noise [N, 2, 2]) -> the updated (mean, covariance)."""
    if len(mean) == 0:
        return mean, covariance
    innovation = measured - mean[:, part]  # [N, 2]
    s = covariance[:, part, part] + noise  # [N, 2, 2]
    gain = covariance[:, :, part] @ inverse_2x2(s)  # [N, 4, 2]
    new_mean = mean + np.einsum("nij,nj->ni", gain, innovation)
    new_covariance = covariance - gain @ covariance[:, part, :]  # [N, 4, 4]
    new_covariance = 0.5 * (new_covariance + np.swapaxes(new_covariance, 1, 2))  # keep it symmetric
    return new_mean, new_covariance


def mahalanobis_squared(
    predicted: np.ndarray, position_covariance: np.ndarray, points: np.ndarray, noise_var: float
) -> np.ndarray:
    """Predicted centres [T, 2] with covariances [T, 2, 2], detection centres [D, 2] -> [T, D] squared Mahalanobis
    distances under the track's spread plus a detection's noise variance."""
    s_inverse = inverse_2x2(position_covariance + noise_var * np.eye(2))  # [T, 2, 2]
    dx = points[None, :, 0] - predicted[:, 0, None]  # [T, D]
    dy = points[None, :, 1] - predicted[:, 1, None]
    a, b, d = s_inverse[:, 0, 0, None], s_inverse[:, 0, 1, None], s_inverse[:, 1, 1, None]  # [T, 1] each
    return a * dx * dx + 2.0 * b * dx * dy + d * dy * dy


def moving_probability(velocity: np.ndarray, covariance: np.ndarray, prior_std: float, prior: float) -> np.ndarray:
    """The probability that a track moves at all, against being parked (v = 0): velocity [N, 2] and its covariance
    [N, 2, 2] from a filter whose velocity prior was N(0, prior_std^2 I), and the prior probability of moving -> [N].

    The Savage-Dickey ratio of the nested models: Bayes factor (moving : parked) = prior density at v = 0 / posterior
    density at v = 0 = N(0; 0, prior_std^2 I) / N(0; v, P), so logit p = logit(prior) + v' P^-1 v / 2
    + log det(P) / 2 - 2 log(prior_std). A track with no evidence keeps the prior; one whose velocity is not
    distinguishable from 0 tends to parked."""
    determinant = covariance[:, 0, 0] * covariance[:, 1, 1] - covariance[:, 0, 1] ** 2  # [N]
    distance_sq = np.einsum("ni,nij,nj->n", velocity, inverse_2x2(covariance), velocity)
    logit = math.log(prior / (1.0 - prior)) + 0.5 * distance_sq + 0.5 * np.log(determinant) - 2.0 * math.log(prior_std)
    return 1.0 / (1.0 + np.exp(-np.clip(logit, -50.0, 50.0)))
