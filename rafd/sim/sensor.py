"""Navtech CTS350-X-like scanning radar: scatterers -> polar power (400 azimuths) -> Cartesian uint8 scan."""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from rafd.geometry import RADIATE_RESOLUTION, RADIATE_SCAN_SIZE
from rafd.polar import PolarConventions
from rafd.sim.scene import Scatterers


@dataclass(frozen=True)
class Difficulty:
    """Knobs scaling the nuisance returns; 1.0 matches the real tiny_foggy sample's statistics."""

    clutter: float = 1.0  # diffuse roadside patches, flickering clutter, interference rays
    ghosts: float = 1.0  # multipath ghosts of vehicles (probability and strength)
    noise: float = 1.0  # receiver noise floor power

    def __post_init__(self) -> None:
        for name in ("clutter", "ghosts", "noise"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0.0):
                raise ValueError(f"difficulty {name} must be a finite number >= 0, got {getattr(self, name)}")


@dataclass(frozen=True)
class NavtechConfig:
    azimuths: int = 400  # 0.9 degree azimuth bins
    range_bin: float = RADIATE_RESOLUTION / 2.0  # metres; finer than a pixel so speckle shows as grain
    disc_radius_pixels: float = RADIATE_SCAN_SIZE / 2.0  # RADIATE scans are black beyond 576 px (100 m)
    beam_sigma_bins: float = 0.85  # ~1.8 degree 3 dB beam width
    azimuth_sidelobe: float = 0.015  # power of the wide azimuth sidelobe relative to the main lobe
    range_sigma_bins: float = 1.3
    radial_streak: float = 0.02  # fraction of an azimuth's echo energy smeared along its whole ray
    shadow: float = 0.25  # power left behind an occluder (diffraction, multipath)
    shadow_margin: float = 0.7  # metres behind the nearest occluder before the shadow starts
    gain: float = 18.0  # grey level per unit amplitude (noise floor power = 1)
    attenuation_range: float = 45.0  # metres: signal power falls as 1 / (1 + r / this)


@dataclass(frozen=True)
class Echoes:
    azimuth: np.ndarray  # [N] continuous azimuth bins in [0, A)
    ranges: np.ndarray  # [N] metres
    power: np.ndarray  # [N]
    lit: np.ndarray  # [N] bool: not in an occluder's shadow
    owner: np.ndarray  # [N] scatterer owner (-1 static world, else road-user index)


def _gaussian(sigma: float, radius: int) -> np.ndarray:
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    return np.exp(-0.5 * (x / sigma) ** 2)  # peak 1: a point target keeps its power at its centre


class NavtechSensor:
    """Renders one scan per call; the Cartesian image is size x size pixels at `resolution`, radar at the centre."""

    def __init__(self, size: int, resolution: float = RADIATE_RESOLUTION, config: NavtechConfig = NavtechConfig()):
        self.size, self.resolution, self.config = size, resolution, config
        disc = config.disc_radius_pixels * resolution
        self.max_range = min(size / 2.0 * math.sqrt(2.0) * resolution, disc)  # metres rendered
        self.num_bins = int(math.ceil(self.max_range / config.range_bin)) + 2
        self.ranges = (np.arange(self.num_bins) + 0.5) * config.range_bin  # [R] bin centres
        # Azimuth kernel: main lobe + wide sidelobe; wrapped padding makes it circular.
        self._pad = 12
        main = _gaussian(config.beam_sigma_bins, self._pad)
        self._azimuth_kernel = ((1 - config.azimuth_sidelobe) * main + config.azimuth_sidelobe * _gaussian(5.0, self._pad)).astype(np.float32)
        self._range_kernel = _gaussian(config.range_sigma_bins, 3).astype(np.float32)
        self._map_x, self._map_y = self._cartesian_maps()

    def _cartesian_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """Per output pixel centre: the (range bin, padded azimuth row) it samples, float32 [S, S] each."""
        cfg = self.config
        centres = (np.arange(self.size, dtype=np.float64) + 0.5 - self.size / 2.0) * self.resolution
        x, y = np.meshgrid(centres, -centres, indexing="xy")  # ego x right, y up
        r = np.hypot(x, y)
        theta = np.mod(np.arctan2(x, y), 2 * np.pi)  # clockwise from forward, like the Navtech's sweep
        map_x = r / cfg.range_bin - 0.5
        map_x[r > cfg.disc_radius_pixels * self.resolution] = -10.0  # outside the disc -> border (0)
        map_y = theta / (2 * np.pi) * cfg.azimuths - 0.5 + 1.0  # +1: one wrapped row padded on top
        return map_x.astype(np.float32), map_y.astype(np.float32)

    @property
    def polar_conventions(self) -> PolarConventions:
        """Where to_cartesian places the samples of the transposed [R, A] polar: bin centres, radar at S/2."""
        return PolarConventions(azimuth_offset=0.5, range_offset=0.5, range_bin=self.config.range_bin,
                                centre_offset=(0.0, 0.0))

    def polar_coordinates(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """[N, 2] ego metres -> ([N] continuous azimuth bins in [0, A), [N] ranges in metres)."""
        theta = np.mod(np.arctan2(xy[:, 0], xy[:, 1]), 2 * np.pi)
        return theta / (2 * np.pi) * self.config.azimuths, np.hypot(xy[:, 0], xy[:, 1])

    def illuminate(self, scatterers: Scatterers) -> "Echoes":
        """Ego-frame scatterers -> the echoes inside the scan after facing, range and occlusion: a surface facing away returns nothing; behind the nearest occluder of an azimuth only
        `shadow` of the power survives."""
        cfg = self.config
        azimuth, rng_m = self.polar_coordinates(scatterers.xy)
        inside = (rng_m > 1.0) & (rng_m < self.max_range)
        towards = -scatterers.xy / np.maximum(rng_m, 1e-6)[:, None]
        facing = np.einsum("ij,ij->i", scatterers.normal, towards)  # cos(incidence); 0 for isotropic
        oriented = np.any(scatterers.normal != 0, axis=1)
        inside &= ~oriented | (facing > 0.02)
        power = scatterers.amplitude * np.where(oriented, 0.2 + 0.8 * np.clip(facing, 0, 1), 1.0)
        bins = np.minimum(azimuth.astype(np.int64), cfg.azimuths - 1)
        nearest = np.full(cfg.azimuths, np.inf)
        blocking = inside & scatterers.occluder
        np.minimum.at(nearest, bins[blocking], rng_m[blocking])
        shadowed = rng_m > nearest[bins] + cfg.shadow_margin
        power = np.where(shadowed, power * cfg.shadow, power) / (1.0 + rng_m / cfg.attenuation_range)
        return Echoes(azimuth[inside], rng_m[inside], power[inside], (~shadowed)[inside], scatterers.owner[inside])

    def accumulate(self, azimuth: np.ndarray, ranges: np.ndarray, power: np.ndarray) -> np.ndarray:
        """Point returns -> [A, R] polar power, each cell keeping its dominant scatterer."""
        cfg = self.config
        rows = np.mod(azimuth.astype(np.int64), cfg.azimuths)
        cols = np.clip((ranges / cfg.range_bin).astype(np.int64), 0, self.num_bins - 1)
        flat = np.zeros(cfg.azimuths * self.num_bins)
        np.maximum.at(flat, rows * self.num_bins + cols, power)
        return flat.reshape(cfg.azimuths, self.num_bins)  # [A, R]

    def receive(self, signal: np.ndarray, rng: np.random.Generator, difficulty: Difficulty) -> np.ndarray:
        """[A, R] echo power -> [A, R] float32 grey levels: beam and range blur, radial streaks,
        noise floor with near-range leakage and interference rays, speckle, amplitude detection."""
        cfg = self.config
        padded = np.concatenate([signal[-self._pad :], signal, signal[: self._pad]]).astype(np.float32)
        blurred = cv2.sepFilter2D(padded, -1, self._range_kernel, self._azimuth_kernel, borderType=cv2.BORDER_CONSTANT)
        blurred = blurred[self._pad : -self._pad].astype(np.float64)  # [A, R]
        # Strong echoes leak along their whole ray (phase noise / range sidelobes): the radial lines.
        energy = blurred.sum(1, keepdims=True) * cfg.range_bin  # [A, 1]
        streak = cfg.radial_streak * energy * np.exp(-self.ranges / 60.0)[None] / 10.0
        floor = difficulty.noise * (1.0 + 7.0 * np.exp(-self.ranges / 2.5))[None]  # [1, R]
        near = rng.lognormal(0.0, 0.9, (cfg.azimuths, 1)) * 3.0 * np.exp(-self.ranges / 3.0)[None]  # centre starburst
        rays = np.ones((cfg.azimuths, 1))
        for row in rng.integers(2, cfg.azimuths - 2, rng.poisson(1.5 * difficulty.clutter)):
            rays[row - int(rng.integers(0, 2)) : row + int(rng.integers(1, 3))] *= rng.uniform(1.8, 3.5)
        noise = (floor + near * difficulty.noise) * rays
        speckle_noise = rng.standard_exponential(blurred.shape)
        speckle_echo = rng.gamma(2.0, 0.5, blurred.shape)
        power = noise * speckle_noise + (blurred + streak) * speckle_echo
        return (cfg.gain * np.sqrt(power)).astype(np.float32)

    def to_cartesian(self, polar: np.ndarray) -> np.ndarray:
        """[A, R] grey levels -> [S, S] uint8 Cartesian scan (bilinear, wrapped at azimuth 0)."""
        padded = np.concatenate([polar[-1:], polar, polar[:1]])  # [A + 2, R]
        image = cv2.remap(padded, self._map_x, self._map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return np.clip(np.rint(image), 0, 255).astype(np.uint8)
