"""rafd.odometry.ecc: inverse-compositional ECC recovers a known Euclidean warp and refuses a blank template."""

import math

import cv2
import numpy as np

from rafd.odometry.ecc import EccTemplate, align, euclidean_matrix

SIZE = 128


def _scene() -> np.ndarray:
    """[SIZE, SIZE] float32: a few blurred blobs and bars, structure in every direction."""
    rng = np.random.default_rng(3)
    image = np.zeros((SIZE, SIZE), np.float32)
    for _ in range(25):
        u, v = rng.integers(15, SIZE - 15, size=2)
        cv2.circle(image, (int(u), int(v)), int(rng.integers(2, 6)), float(rng.uniform(0.5, 1.0)), -1)
    cv2.line(image, (20, 30), (100, 40), 0.8, 2)
    return cv2.GaussianBlur(image, (0, 0), 2.0)


def test_align_recovers_a_known_warp_from_a_nearby_start() -> None:
    previous = _scene()
    truth = euclidean_matrix(math.radians(1.5), 2.0, -1.0, SIZE)[:2].astype(np.float32)
    current = cv2.warpAffine(previous, truth, (SIZE, SIZE), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    template = EccTemplate.of(current)
    assert template is not None
    start = euclidean_matrix(0.0, 0.0, 0.0, SIZE)[:2].astype(np.float32)
    result = align(template, previous, start, 30, 1e-6)
    assert result is not None
    warp, rho = result
    yaw = math.atan2(float(warp[1, 0]), float(warp[0, 0]))
    assert abs(math.degrees(yaw) - 1.5) < 0.05
    assert np.abs(warp[:, 2] - truth[:, 2]).max() < 0.1
    assert rho > 0.95


def test_blank_template_has_no_precomputation() -> None:
    assert EccTemplate.of(np.zeros((SIZE, SIZE), np.float32)) is None
