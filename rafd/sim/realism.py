"""How much simulated scans look like real ones, measured without labels (scan images only).

Five kinds of measure, each a row of `realism_table` (real value, simulated value, distance):
- grey quantiles per range: p50 / p90 / p99 of the grey levels in thin rings at 3, 5, 10, 20 and 40 m (the noise
  floor's shape over range, and how bright the returns are); distance = mean |difference| of the three;
- speckle grain: the along-range correlation length (metres at which the autocorrelation of the detrended grey
  level along each ray falls to 0.5), 10-60 m;
- azimuth striping: the relative spread of the per-azimuth mean grey level after removing its slow trend (how much
  whole beams differ from their neighbours), 10-60 m;
- scan-to-scan stability: how much the bright returns of one scan are still there in the next, once the previous
  scan is aligned to the current one by radar odometry (rafd.odometry.registration, the same estimator for both
  kinds): walls and kerbs persist, spray and multipath flicker;
- a real-vs-simulated patch classifier: a small CNN trained on 48 x 48 px patches of half the frames of each kind and
  tested on patches of the other half, and the other way round (2-fold); held-out accuracy 50% = indistinguishable,
  100% = trivially told apart.
Scans are 1152 px Cartesian scans on RADIATE's grid (radar at the centre); polar measures resample them with
cv2.warpPolar (one sample per pixel along range, 1440 azimuths).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from rafd.geometry import RADIATE_RESOLUTION

RING_RANGES_M = (3.0, 5.0, 10.0, 20.0, 40.0)
RING_HALF_WIDTH = 0.1  # rings span r * (1 -+ this)
QUANTILES = (50, 90, 99)
BAND_M = (10.0, 60.0)  # range band of the speckle and striping measures
POLAR_ANGLES = 1440  # 0.25 degree: the Navtech's 0.9 degree beams span 3.6 samples
STABILITY_BAND_M = (5.0, 40.0)  # range band of the scan-to-scan measure
BRIGHT_SHARE = 0.05  # the brightest share of a pair's pixels (by their mean) that the stability correlates
PATCH = 48  # classifier patch side, pixels (8.3 m)
PATCH_MAX_RANGE_M = 60.0  # patches are cut where both kinds of scan have content


@dataclass(frozen=True)
class Row:
    name: str
    real: str
    simulated: str
    distance: float  # how far the simulation is from the real scans on this row (lower is closer)
    unit: str = ""


def _radius_m(size: int, resolution: float) -> np.ndarray:
    centres = (np.arange(size) + 0.5 - size / 2.0) * resolution
    return np.hypot(*np.meshgrid(centres, centres))


def ring_quantiles(scans: Sequence[np.ndarray], resolution: float = RADIATE_RESOLUTION) -> dict[float, np.ndarray]:
    """{range m: [p50, p90, p99]} of the grey levels in the ring around each range, pooled over the scans."""
    radius = _radius_m(scans[0].shape[0], resolution)
    out = {}
    for r in RING_RANGES_M:
        ring = (radius > r * (1 - RING_HALF_WIDTH)) & (radius < r * (1 + RING_HALF_WIDTH))
        values = np.concatenate([np.asarray(scan)[ring] for scan in scans]).astype(np.float64)
        out[r] = np.percentile(values, QUANTILES)
    return out


def polar_view(scan: np.ndarray) -> np.ndarray:
    """[S, S] Cartesian scan -> float32 [POLAR_ANGLES, S/2] (rows: azimuth, columns: range, one pixel per sample)."""
    size = scan.shape[0]
    centre = (size / 2.0, size / 2.0)  # cv2 pixel centres are integers: the radar sits between four pixels
    return cv2.warpPolar(
        np.asarray(scan, np.float32),
        (size // 2, POLAR_ANGLES),
        centre,
        size / 2.0,
        cv2.INTER_LINEAR | cv2.WARP_POLAR_LINEAR,
    )


def _band(polar: np.ndarray, resolution: float) -> np.ndarray:
    lo, hi = (int(round(r / resolution)) for r in BAND_M)
    return polar[:, lo:hi]


def speckle_grain_m(scans: Sequence[np.ndarray], resolution: float = RADIATE_RESOLUTION) -> float:
    """Along-range correlation length (m): lag where the mean autocorrelation of detrended rays falls to 0.5."""
    max_lag = 12
    curves = []
    for scan in scans:
        rays = _band(polar_view(scan), resolution).astype(np.float64)  # [A, R]
        detrended = rays - cv2.blur(rays, (int(round(3.0 / resolution)) | 1, 1))  # minus a 3 m moving mean
        detrended -= detrended.mean(axis=1, keepdims=True)
        variance = (detrended**2).mean(axis=1)
        keep = variance > 1e-6
        rows = detrended[keep]
        curve = [1.0] + [
            float(((rows[:, :-k] * rows[:, k:]).mean(axis=1) / variance[keep]).mean()) for k in range(1, max_lag + 1)
        ]
        curves.append(curve)
    curve = np.mean(curves, axis=0)
    below = np.flatnonzero(curve < 0.5)
    if not len(below):
        return max_lag * resolution
    k = below[0]  # interpolate between lags k - 1 and k
    return float((k - 1 + (curve[k - 1] - 0.5) / (curve[k - 1] - curve[k])) * resolution)


def azimuth_striping(scans: Sequence[np.ndarray], resolution: float = RADIATE_RESOLUTION) -> float:
    """Relative spread of per-azimuth mean grey (10-60 m) around its 9-degree moving mean, averaged over scans."""
    values = []
    for scan in scans:
        means = _band(polar_view(scan), resolution).mean(axis=1)  # [A]
        window = int(round(9.0 / 360.0 * POLAR_ANGLES))
        padded = np.concatenate([means[-window:], means, means[:window]])  # circular
        trend = np.convolve(padded, np.ones(window) / window, "same")[window:-window]
        values.append(float(np.std(means - trend) / max(means.mean(), 1e-6)))
    return float(np.mean(values))


def scan_to_scan_stability(sequences: Sequence[Sequence[np.ndarray]], resolution: float = RADIATE_RESOLUTION) -> float:
    """Median over consecutive scan pairs of the correlation of their bright returns after ego alignment.

    The previous scan is warped onto the current one by the radar odometry's relative pose, both are smoothed over
    one pixel (odometry errors of a pixel should not count as flicker), and the grey levels of the brightest
    BRIGHT_SHARE of the 5-40 m pixels, ranked by the pair's mean, are correlated: 1 = every bright return persists,
    0 = bright returns are redrawn every scan."""
    from rafd.odometry.registration import estimate_relative_pose, pose_to_warp

    values, in_band = [], {}  # in_band: scan size -> the 5-40 m ring's pixels
    for scans in sequences:
        for previous, current in zip(scans[:-1], scans[1:]):
            size = current.shape[0]
            if size not in in_band:
                radius = _radius_m(size, resolution)
                in_band[size] = (radius > STABILITY_BAND_M[0]) & (radius < STABILITY_BAND_M[1])
            warp = pose_to_warp(estimate_relative_pose(previous, current, resolution), size, resolution)
            moved = cv2.warpAffine(
                np.asarray(previous, np.float32), warp, (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
            )  # previous on the current grid
            band = in_band[size] & (moved > 0)
            before = cv2.GaussianBlur(moved, (0, 0), 1.0)[band]
            after = cv2.GaussianBlur(np.asarray(current, np.float32), (0, 0), 1.0)[band]
            mean = (before + after) / 2.0
            bright = mean >= np.percentile(mean, 100.0 * (1.0 - BRIGHT_SHARE))
            if before[bright].std() > 0 and after[bright].std() > 0:
                values.append(float(np.corrcoef(before[bright], after[bright])[0, 1]))
    if not values:
        raise ValueError("scan-to-scan stability needs a sequence of at least 2 scans with some structure")
    return float(np.median(values))


def _patches(
    scans: Sequence[np.ndarray], count: int, rng: np.random.Generator, resolution: float = RADIATE_RESOLUTION
) -> np.ndarray:
    """`count` random PATCH x PATCH patches per scan whose centres lie within PATCH_MAX_RANGE_M -> uint8 [N, P, P]."""
    out = []
    for scan in scans:
        size = scan.shape[0]
        reach = min(PATCH_MAX_RANGE_M / resolution, size / 2.0 - PATCH) / math.sqrt(2.0)
        centres = rng.uniform(size / 2.0 - reach, size / 2.0 + reach, (count, 2)).astype(int)
        for u, v in centres:
            out.append(scan[v - PATCH // 2 : v + PATCH // 2, u - PATCH // 2 : u + PATCH // 2])
    return np.stack(out)


def patch_classifier_accuracy(
    real: Sequence[np.ndarray],
    simulated: Sequence[np.ndarray],
    seed: int = 0,
    steps: int = 400,
    patches_per_scan: int = 200,
) -> float:
    """Held-out accuracy of a small CNN telling real from simulated patches: scans split in halves by index (time),
    trained on one half and tested on the other, both ways, averaged."""
    half_real, half_sim = len(real) // 2, len(simulated) // 2
    if min(half_real, half_sim) < 1:
        raise ValueError("the patch classifier needs at least 2 real and 2 simulated scans")
    folds = [((real[:half_real], simulated[:half_sim]), (real[half_real:], simulated[half_sim:]))]
    folds.append((folds[0][1], folds[0][0]))
    return float(
        np.mean(
            [_fold_accuracy(train, test, seed + k, steps, patches_per_scan) for k, (train, test) in enumerate(folds)]
        )
    )


def _fold_accuracy(train: tuple, test: tuple, seed: int, steps: int, patches_per_scan: int) -> float:
    """Train on (real, simulated) scans `train`, return the accuracy on `test`."""
    import torch
    from torch import nn

    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)

    def data(real_scans, sim_scans):
        a = _patches(real_scans, patches_per_scan, rng)
        b = _patches(sim_scans, patches_per_scan * len(real_scans) // max(len(sim_scans), 1), rng)
        n = min(len(a), len(b))  # balanced classes
        x = np.concatenate([a[:n], b[:n]]).astype(np.float32)[:, None] / 255.0
        y = np.concatenate([np.ones(n), np.zeros(n)]).astype(np.float32)
        return torch.from_numpy(x), torch.from_numpy(y)

    x_train, y_train = data(*train)
    x_test, y_test = data(*test)
    net = nn.Sequential(
        nn.Conv2d(1, 16, 3, padding=1),
        nn.ReLU(),
        nn.MaxPool2d(2),
        nn.Conv2d(16, 32, 3, padding=1),
        nn.ReLU(),
        nn.MaxPool2d(2),
        nn.Conv2d(32, 32, 3, padding=1),
        nn.ReLU(),
        nn.AdaptiveAvgPool2d(1),
        nn.Flatten(),
        nn.Linear(32, 1),
    )
    optimizer = torch.optim.Adam(net.parameters(), lr=2e-3)
    for _ in range(steps):
        pick = torch.from_numpy(rng.integers(0, len(x_train), 64))
        loss = nn.functional.binary_cross_entropy_with_logits(net(x_train[pick])[:, 0], y_train[pick])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        predicted = torch.cat([net(x_test[i : i + 512])[:, 0] for i in range(0, len(x_test), 512)]) > 0
    return float((predicted.float() == y_test).float().mean())


CLASSIFIER_SEEDS = 2  # independent classifiers (each 2-fold) averaged: one alone varies by several points


def realism_table(
    real_sequences: Sequence[Sequence[np.ndarray]],
    simulated_sequences: Sequence[Sequence[np.ndarray]],
    classifier: bool = True,
    seed: int = 0,
    classifier_steps: int = 400,
) -> list[Row]:
    """Every measure of the module docstring for two lists of sequences (each a list of uint8 [1152, 1152] scans in
    time order; the scan-to-scan measure pairs consecutive scans of a sequence, the others pool every scan)."""
    real = [scan for scans in real_sequences for scan in scans]
    simulated = [scan for scans in simulated_sequences for scan in scans]
    rows = []
    real_q, sim_q = ring_quantiles(real), ring_quantiles(simulated)
    for r in RING_RANGES_M:
        rows.append(
            Row(
                f"grey p50/p90/p99 at {r:g} m",
                "/".join(f"{v:.0f}" for v in real_q[r]),
                "/".join(f"{v:.0f}" for v in sim_q[r]),
                float(np.abs(real_q[r] - sim_q[r]).mean()),
                "grey",
            )
        )
    grain_real, grain_sim = speckle_grain_m(real), speckle_grain_m(simulated)
    rows.append(
        Row("speckle grain along range", f"{grain_real:.2f}", f"{grain_sim:.2f}", abs(grain_real - grain_sim), "m")
    )
    stripe_real, stripe_sim = azimuth_striping(real), azimuth_striping(simulated)
    rows.append(Row("azimuth striping", f"{stripe_real:.3f}", f"{stripe_sim:.3f}", abs(stripe_real - stripe_sim)))
    stable_real, stable_sim = scan_to_scan_stability(real_sequences), scan_to_scan_stability(simulated_sequences)
    rows.append(
        Row(
            "scan-to-scan stability of bright returns",
            f"{stable_real:.2f}",
            f"{stable_sim:.2f}",
            abs(stable_real - stable_sim),
        )
    )
    if classifier:
        accuracy = float(
            np.mean(
                [
                    patch_classifier_accuracy(real, simulated, seed=seed + 10 * k, steps=classifier_steps)
                    for k in range(CLASSIFIER_SEEDS)
                ]
            )
        )
        rows.append(
            Row(
                "patch classifier, held-out accuracy",
                "50%",
                f"{100 * accuracy:.1f}%",
                100 * abs(accuracy - 0.5),
                "points above 50%",
            )
        )
    return rows


def format_table(rows: Sequence[Row]) -> str:
    lines = ["| measure | real | simulated | distance |", "|---|---|---|---|"]
    for row in rows:
        unit = f" {row.unit}" if row.unit else ""
        lines.append(f"| {row.name} | {row.real} | {row.simulated} | {row.distance:.3f}{unit} |")
    return "\n".join(lines)


def format_tables(tables: Mapping[str, Sequence[Row]]) -> str:
    """Several references against the same simulated scans, side by side: per reference its real value and the
    simulated scans' distance to it (the simulated value is the same for every reference)."""
    names = list(tables)
    first = list(tables[names[0]])
    header = "| measure | simulated | " + " | ".join(f"{n} | distance to {n}" for n in names) + " |"
    lines = [header, "|" + "---|" * (2 + 2 * len(names))]
    for index, row in enumerate(first):
        unit = f" {row.unit}" if row.unit else ""
        cells = " | ".join(f"{tables[n][index].real} | {tables[n][index].distance:.3f}{unit}" for n in names)
        lines.append(f"| {row.name} | {row.simulated} | {cells} |")
    return "\n".join(lines)
