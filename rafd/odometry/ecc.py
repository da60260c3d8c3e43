"""Inverse-compositional ECC for a Euclidean warp: the refinement step of radar odometry (rafd.odometry.registration).

ECC (Evangelidis & Psarakis, "Parametric image alignment using enhanced correlation coefficient maximization",
PAMI 2008) maximises the zero-mean normalised correlation between a template and the warped input; opencv's
findTransformECC is its forward-additive form, which warps the input's gradients and rebuilds the Jacobian and
Hessian every iteration. The inverse-compositional form (the paper's section 4) linearises the TEMPLATE instead:
its steepest-descent images, their Hessian and the template's own projections are computed once per template, and
an iteration is one warp of the input and four dot products. Same criterion, same closed-form step; the warp update
composes with the step's inverse.

Roles as in rafd.odometry.registration: the template is the CURRENT scan (its pixel grid u), the input the PREVIOUS
one, and the warp W maps u to previous-scan pixels, current(u) ~ previous(W u) (cv2.warpAffine(previous, W,
WARP_INVERSE_MAP) predicts the current scan). Euclidean parameters (yaw about the image centre, shift x, shift y in
pixels) keep rotation and shift decorrelated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class EccTemplate:
    """What IC-ECC precomputes from one template (an [n, n] float32 image)."""

    size: int
    zero_mean: np.ndarray  # [N] float32 template, mean removed (N = n * n)
    steepest: np.ndarray  # [3, N] float32: d template(W(dp; u)) / d (yaw, x, y) at dp = 0, each row zero-mean
    hessian_inv: np.ndarray  # [3, 3] float64 inverse of steepest @ steepest.T
    projection: np.ndarray  # [3] float64 steepest @ zero_mean
    norm_sq: float  # |zero_mean|^2
    projected_sq: float  # zero_mean's squared norm within the steepest-descent span (t^T P t)

    @classmethod
    def of(cls, template: np.ndarray) -> EccTemplate | None:
        """The template's precomputation, None when it holds no structure (a singular Hessian)."""
        image = np.asarray(template, np.float32)
        n = image.shape[0]
        grad_x = cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)  # [n, n] d/du, in intensity per pixel
        grad_y = cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)  # [n, n] d/dv
        coords = np.arange(n, dtype=np.float32) - (n - 1) / 2.0
        x, y = coords[None, :], coords[:, None]  # [1, n], [n, 1] pixels from the centre
        # dW/dyaw at 0 for W(u) = R(yaw) (u - c) + c + shift: (-y, x); dW/dshift = identity
        images = np.empty((3, n, n), np.float32)  # filled in place (no stacked copy)
        np.subtract(x * grad_y, y * grad_x, out=images[0])
        images[1], images[2] = grad_x, grad_y
        steepest = images.reshape(3, -1)  # [3, N]
        steepest -= steepest.mean(axis=1, keepdims=True)
        zero_mean = image.reshape(-1) - image.mean()  # [N]
        # [3, 3] from six row dot products: numpy's [3, N] @ [N, 3] is 5x slower than BLAS's dot at this shape
        hessian = np.empty((3, 3))
        for i in range(3):
            for j in range(i, 3):
                hessian[i, j] = hessian[j, i] = float(steepest[i] @ steepest[j])
        if not np.isfinite(hessian).all() or np.linalg.cond(hessian) > 1e12:
            return None
        hessian_inv = np.linalg.inv(hessian)
        projection = (steepest @ zero_mean).astype(np.float64)  # [3]
        norm_sq = float(zero_mean @ zero_mean)
        return cls(
            n, zero_mean, steepest, hessian_inv, projection, norm_sq, float(projection @ hessian_inv @ projection)
        )


def euclidean_matrix(yaw: float, shift_x: float, shift_y: float, size: int) -> np.ndarray:
    """[3, 3] W(dp): u -> R(yaw) (u - c) + c + shift, c the centre of an [size, size] image."""
    c, s = math.cos(yaw), math.sin(yaw)
    centre = (size - 1) / 2.0
    rotation = np.array([[c, -s], [s, c]])
    offset = np.array([centre, centre]) - rotation @ np.array([centre, centre]) + np.array([shift_x, shift_y])
    matrix = np.eye(3)
    matrix[:2, :2], matrix[:2, 2] = rotation, offset
    return matrix


def align(
    template: EccTemplate, image: np.ndarray, warp: np.ndarray, iterations: int, eps: float
) -> tuple[np.ndarray, float] | None:
    """Maximise the ECC between the template and `image` [n, n] warped by a 2x3 `warp` (template(u) ~ image(W u)),
    from `warp` -> (the refined 2x3 float32 warp, its correlation coefficient), or None where the step is undefined
    (the correlation's projection is not positive: no convergence from this start). Stops after `iterations` steps or
    once a step moves the warp less than `eps` (yaw in radians, shift in pixels, together)."""
    n = template.size
    current = np.vstack([np.asarray(warp, np.float64), [0.0, 0.0, 1.0]])  # [3, 3]
    t, g = template.zero_mean, template.steepest
    source = np.asarray(image, np.float32)
    rho = -1.0
    for _ in range(iterations):
        warped = cv2.warpAffine(
            source,
            current[:2].astype(np.float32),
            (n, n),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_CONSTANT,
        ).reshape(-1)  # [N] image(W u)
        # the template's rows and steepest-descent images are zero-mean, so the warped image's mean only enters its
        # own norm: no mean-free copy of it
        mean = float(warped.mean())
        i_proj = (g @ warped).astype(np.float64)  # [3]
        i_norm_sq = max(float(warped @ warped) - warped.size * mean * mean, 0.0)
        correlation = float(warped @ t)
        rho = correlation / math.sqrt(max(i_norm_sq * template.norm_sq, 1e-30))
        # the step maximising the linearised ECC (the paper's eq. 27 with the template linearised)
        denominator = correlation - float(i_proj @ template.hessian_inv @ template.projection)
        if denominator <= 0:
            return None
        lam = (template.norm_sq - template.projected_sq) / denominator
        step = template.hessian_inv @ (lam * i_proj - template.projection)  # [3] (yaw, x, y)
        current = current @ np.linalg.inv(euclidean_matrix(float(step[0]), float(step[1]), float(step[2]), n))
        if float(np.linalg.norm(step)) < eps:
            break
    return current[:2].astype(np.float32), rho
