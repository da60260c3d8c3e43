"""Navtech CTS350-X-like scanning radar: scatterers -> polar power (400 azimuths) -> Cartesian uint8 scan.

What the receiver adds, as measured on real RADIATE scans (rafd.sim.realism, label-free): a noise floor that is high
within a few metres, lowest around 5-10 m and rises again with range; speckle correlated over ~0.5 m along range;
whole beams brighter or darker than their neighbours (azimuth striping, half of it repeating every rotation);
bright returns that mostly persist from scan to scan (most point clutter is fixed in the world, rafd.sim.sequence);
radial streaks behind strong returns; and a fixed pattern of the sensor's mounting -- a starburst around the radar
and a bright streak just behind it, in the sensor's own frame, in every scan. Weather adds two-way attenuation and
(rain) diffuse backscatter near the radar.
A drive's conditions (gain, floor, striping, speckle grain, weather) are drawn once per sequence (Conditions).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from rafd.geometry import RADIATE_RESOLUTION, RADIATE_SCAN_SIZE
from rafd.scans.polar import PolarConventions
from rafd.sim.scene import Scatterers

MOUNT_GAIN = 3.0  # the mounting pattern's power scales by this (matched to the real 3 m ring)
BEAM_CORRELATION = 0.0  # azimuth bins: Gaussian correlation of the per-beam gains (0 = independent beams)
NOISE_GRAIN = 0.7  # range bins: the receiver noise's own correlation (echo speckle has Conditions.speckle_grain)
FLOOR_FAR_SCALE = 1.0  # scales Conditions.floor_far (the floor's rise with range)
NOISE_FLOOR = 0.55  # receiver noise power (grey ~13 where nothing reflects, as on real carriageways)
CLUTTER_PERSISTENCE_RANGE = (0.7, 1.0)  # real bright returns mostly persist from scan to scan (rafd.sim.realism)
STRIPING_FIXED = 0.5  # share of the per-beam log-gain variance fixed in the sensor's frame (repeats every rotation)
# share of the echo power that is speckle, redrawn every scan (the rest, dominant scatterers, persists): puts the
# scan-to-scan stability of bright returns at the real sample's (rafd.sim.realism)
ECHO_SPECKLE = 0.3
WEATHERS = ("clear", "fog", "rain")
WEATHER_PROBABILITIES = (0.45, 0.3, 0.25)  # a drive's weather, when not forced
MOUNT_SEED = 20191127  # the sensor's fixed mounting pattern is the same in every drive (one vehicle, one radar)


@dataclass(frozen=True)
class Difficulty:
    """User knobs scaling the nuisance returns (1.0 = as the defaults draw them)."""

    clutter: float = 1.0  # vegetation, ground, flickering clutter, interference rays
    ghosts: float = 1.0  # multipath ghosts of vehicles (probability and strength)
    noise: float = 1.0  # receiver noise floor power

    def __post_init__(self) -> None:
        for name in ("clutter", "ghosts", "noise"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0.0):
                raise ValueError(f"difficulty {name} must be a finite number >= 0, got {getattr(self, name)}")


@dataclass(frozen=True)
class Conditions:
    """One drive's sensing conditions, drawn per sequence (every knob randomised in the training data)."""

    weather: str  # "clear" | "fog" | "rain"
    gain: float  # receiver gain: grey levels scale by this
    floor_near: float  # floor excess within a few metres (power, noise = 1)
    floor_far: float  # floor rise at 40 m (power)
    striping: float  # std of the per-beam log gain
    speckle_grain: float  # along-range correlation of the speckle, Gaussian sigma in range bins
    attenuation: float  # 1/m: two-way power factor exp(-2 attenuation r)
    rain: float  # rain backscatter power near the radar
    vehicle_gain: float  # road users' returns scale by this (wet or foggy scenes look fainter)
    clutter_persistence: float = 0.0  # share of the point clutter fixed in the world (the rest is redrawn per scan)
    beam_seed: int = 0  # draws the per-beam gains that repeat in every scan of the drive (STRIPING_FIXED)

    @classmethod
    def sample(cls, rng: np.random.Generator, weather: str | None = None) -> Conditions:
        """Draw one drive's conditions; `weather` forces its weather instead of drawing it (e.g. to compare with
        real scans taken in that weather). Forcing takes from `rng` exactly what drawing would, so the drive's every
        other draw (its gain, floor, town, traffic) stays as it was: the same drive, in another weather."""
        if weather is not None and weather not in WEATHERS:
            raise ValueError(f"weather must be one of {', '.join(WEATHERS)}, got {weather!r}")
        drawn = str(rng.choice(WEATHERS, p=WEATHER_PROBABILITIES))
        weather = weather or drawn
        # the draws in their historical order (a drive simulated before stays the same drive)
        gain = float(rng.lognormal(0.0, 0.12))
        floor_near, floor_far = float(rng.uniform(2.0, 6.0)), float(rng.uniform(0.3, 1.2))
        striping, speckle_grain = float(rng.uniform(0.15, 0.4)), float(rng.uniform(2.0, 3.6))
        # one-way power attenuation at 77 GHz (ITU-R P.840 / P.838): dense fog up to ~1.2 dB/km, rain of ~2-40 mm/h
        # about 2-15 dB/km
        attenuation = float(
            {"clear": 0.0, "fog": rng.uniform(0.0, 0.0003), "rain": rng.uniform(0.0005, 0.0035)}[weather]
        )
        # The rain backscatter's strength is taken from the stream only where the drive drew rain; a drive forced into
        # rain takes it from a side stream (Generator.spawn leaves the main stream where it is).
        drawn_rain = float(rng.uniform(0.5, 3.0)) if drawn == "rain" else None
        if weather != "rain":
            rain = 0.0
        else:
            rain = drawn_rain if drawn_rain is not None else float(rng.spawn(1)[0].uniform(0.5, 3.0))
        return cls(
            weather=weather,
            gain=gain,
            floor_near=floor_near,
            floor_far=floor_far,
            striping=striping,
            speckle_grain=speckle_grain,
            attenuation=attenuation,
            rain=rain,
            vehicle_gain=float(rng.uniform(0.4, 1.0) if weather != "clear" else rng.uniform(0.7, 1.3)),
            clutter_persistence=float(rng.uniform(*CLUTTER_PERSISTENCE_RANGE)),
            beam_seed=int(rng.integers(2**31)),
        )


@dataclass(frozen=True)
class NavtechConfig:
    azimuths: int = 400  # 0.9 degree azimuth bins
    range_bin: float = RADIATE_RESOLUTION / 2.0  # metres; finer than a pixel so speckle shows as grain
    disc_radius_pixels: float = RADIATE_SCAN_SIZE / 2.0  # RADIATE scans are black beyond 576 px (100 m)
    beam_sigma_bins: float = 0.85  # ~1.8 degree 3 dB beam width
    azimuth_sidelobe: float = 0.015  # power of the wide azimuth sidelobe relative to the main lobe
    range_sigma_bins: float = 1.8  # 0.16 m: real point returns are soft blobs along range too
    speckle_azimuth_sigma: float = 0.7  # adjacent beams overlap (the beam is twice the azimuth step)
    radial_streak: float = 0.0  # fraction of an azimuth's echo energy smeared along its whole ray (real scans: none)
    shadow: float = 0.25  # power left behind an occluder (diffraction, multipath)
    shadow_margin: float = 0.7  # metres behind the nearest occluder before the shadow starts
    gain: float = 17.0  # grey level per unit amplitude (noise floor power = 1)
    # metres: signal power falls as 1 / (1 + r / this); real structure 40 m away is about as bright as at 10 m
    attenuation_range: float = 1000.0
    mount_rays: int = 45  # starburst rays of the mounting pattern
    mount_reach: float = 1.8  # metres over which the starburst rays fade
    mount_streak_azimuth: float = 203.0  # bin of the streak behind the radar (bin 200 = straight back)
    mount_streak_reach: float = 4.0  # metres


@dataclass(frozen=True)
class Echoes:
    azimuth: np.ndarray  # [N] continuous azimuth bins in [0, A)
    ranges: np.ndarray  # [N] metres
    power: np.ndarray  # [N]
    lit: np.ndarray  # [N] bool: not in an occluder's shadow
    owner: np.ndarray  # [N] scatterer owner (-1 static world, else road-user index)
    diffuse: np.ndarray  # [N] bool: summed per polar cell (extended returns)


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
        self._azimuth_kernel = (
            (1 - config.azimuth_sidelobe) * main + config.azimuth_sidelobe * _gaussian(5.0, self._pad)
        ).astype(np.float32)
        self._range_kernel = _gaussian(config.range_sigma_bins, int(math.ceil(3 * config.range_sigma_bins))).astype(
            np.float32
        )
        self._map_x, self._map_y = self._cartesian_maps()
        self.mount = self._mount_pattern()

    @property
    def beam_sigma_rad(self) -> float:
        """Gaussian sigma of the beam across the line of sight, radians."""
        return self.config.beam_sigma_bins * 2.0 * math.pi / self.config.azimuths

    @property
    def range_sigma_m(self) -> float:
        return self.config.range_sigma_bins * self.config.range_bin

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

    def _mount_pattern(self) -> np.ndarray:
        """[A, R] power of the sensor's fixed near-range pattern: starburst rays and the streak just behind it."""
        cfg = self.config
        rng = np.random.default_rng(MOUNT_SEED)
        pattern = np.zeros((cfg.azimuths, self.num_bins))
        rays = rng.choice(cfg.azimuths, cfg.mount_rays, replace=False)
        fall = np.exp(-self.ranges / cfg.mount_reach)  # [R]
        pattern[rays] += rng.uniform(12.0, 60.0, (cfg.mount_rays, 1)) * fall[None]
        pattern += 5.0 * np.exp(-self.ranges / 1.5)[None]  # the disc of leakage right at the radar
        streak = np.exp(-0.5 * ((np.arange(cfg.azimuths) - cfg.mount_streak_azimuth) / 1.2) ** 2)  # [A]
        pattern += 60.0 * streak[:, None] * np.exp(-self.ranges / cfg.mount_streak_reach)[None]
        return pattern * MOUNT_GAIN

    @property
    def polar_conventions(self) -> PolarConventions:
        """Where to_cartesian places the samples of the transposed [R, A] polar: bin centres, radar at S/2."""
        return PolarConventions(
            azimuth_offset=0.5, range_offset=0.5, range_bin=self.config.range_bin, centre_offset=(0.0, 0.0)
        )

    def polar_coordinates(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """[N, 2] ego metres -> ([N] continuous azimuth bins in [0, A), [N] ranges in metres)."""
        theta = np.mod(np.arctan2(xy[:, 0], xy[:, 1]), 2 * np.pi)
        return theta / (2 * np.pi) * self.config.azimuths, np.hypot(xy[:, 0], xy[:, 1])

    def illuminate(self, scatterers: Scatterers, conditions: Conditions | None = None) -> Echoes:
        """Ego-frame scatterers -> the echoes inside the scan after facing, range, weather and occlusion: a surface
        facing away returns nothing; behind the nearest occluder of an azimuth only `shadow` of the power survives."""
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
        attenuation = 0.0 if conditions is None else conditions.attenuation
        power = np.where(shadowed, power * cfg.shadow, power) / (1.0 + rng_m / cfg.attenuation_range)
        power = power * np.exp(-2.0 * attenuation * rng_m)
        return Echoes(
            azimuth[inside],
            rng_m[inside],
            power[inside],
            (~shadowed)[inside],
            scatterers.owner[inside],
            scatterers.diffuse[inside],
        )

    def accumulate(
        self, azimuth: np.ndarray, ranges: np.ndarray, power: np.ndarray, diffuse: np.ndarray | None = None
    ) -> np.ndarray:
        """Point returns -> [A, R] polar power: a cell keeps its dominant point scatterer plus the sum of the
        diffuse ones (extended returns add up incoherently)."""
        cfg = self.config
        rows = np.mod(azimuth.astype(np.int64), cfg.azimuths)
        cols = np.clip((ranges / cfg.range_bin).astype(np.int64), 0, self.num_bins - 1)
        cells = rows * self.num_bins + cols
        diffuse = np.zeros(len(power), bool) if diffuse is None else diffuse
        flat = np.zeros(cfg.azimuths * self.num_bins)
        np.maximum.at(flat, cells[~diffuse], power[~diffuse])
        np.add.at(flat, cells[diffuse], power[diffuse])
        return flat.reshape(cfg.azimuths, self.num_bins)  # [A, R]

    def _speckle(self, rng: np.random.Generator, shape: tuple[int, int], grain: float) -> np.ndarray:
        """Fully developed speckle (unit-mean exponential intensity) correlated over `grain` bins along range."""
        kernel = _gaussian(grain, int(math.ceil(3 * grain))).astype(np.float32)  # along range
        across = _gaussian(self.config.speckle_azimuth_sigma, 2).astype(np.float32)  # across beams
        real = cv2.sepFilter2D(rng.standard_normal(shape).astype(np.float32), -1, kernel, across)
        imag = cv2.sepFilter2D(rng.standard_normal(shape).astype(np.float32), -1, kernel, across)
        intensity = real.astype(np.float64) ** 2 + imag.astype(np.float64) ** 2
        return intensity / (2.0 * float((kernel**2).sum()) * float((across**2).sum()))

    def receive(
        self, signal: np.ndarray, rng: np.random.Generator, difficulty: Difficulty, conditions: Conditions | None = None
    ) -> np.ndarray:
        """[A, R] echo power -> [A, R] float32 grey levels: beam and range blur, radial streaks, the range-dependent
        floor, the mounting pattern, rain backscatter, interference rays, per-beam gain, speckle, detection."""
        cfg = self.config
        conditions = conditions or Conditions("clear", 1.0, 4.0, 0.7, 0.25, 1.5, 0.0, 0.0, 1.0)
        padded = np.concatenate([signal[-self._pad :], signal, signal[: self._pad]]).astype(np.float32)
        blurred = cv2.sepFilter2D(padded, -1, self._range_kernel, self._azimuth_kernel, borderType=cv2.BORDER_CONSTANT)
        blurred = blurred[self._pad : -self._pad].astype(np.float64)  # [A, R]
        # Strong echoes leak along their whole ray (phase noise / range sidelobes): the radial lines.
        energy = blurred.sum(1, keepdims=True) * cfg.range_bin  # [A, 1]
        streak = cfg.radial_streak * energy * np.exp(-self.ranges / 60.0)[None] / 10.0
        floor = (
            NOISE_FLOOR
            * difficulty.noise
            * (
                1.0
                + conditions.floor_near * np.exp(-self.ranges / 2.0)
                + FLOOR_FAR_SCALE * conditions.floor_far * self.ranges / 40.0
            )[None]
        )
        rain = conditions.rain * np.exp(-self.ranges / 25.0)[None]
        rays = np.ones((cfg.azimuths, 1))
        for row in rng.integers(2, cfg.azimuths - 2, rng.poisson(1.5 * difficulty.clutter)):
            rays[row - int(rng.integers(0, 2)) : row + int(rng.integers(1, 3))] *= rng.uniform(1.8, 3.5)
        # per-beam gain (striping), correlated over neighbouring beams like the beam pattern itself
        fixed = np.random.default_rng(conditions.beam_seed).normal(0.0, 1.0, (cfg.azimuths, 1))
        fresh = rng.normal(0.0, 1.0, (cfg.azimuths, 1))
        log_gain = conditions.striping * (math.sqrt(STRIPING_FIXED) * fixed + math.sqrt(1.0 - STRIPING_FIXED) * fresh)
        if BEAM_CORRELATION > 0:
            kernel = _gaussian(BEAM_CORRELATION, int(math.ceil(3 * BEAM_CORRELATION)))
            wrapped = np.concatenate([log_gain[-len(kernel) :], log_gain, log_gain[: len(kernel)]])[:, 0]
            log_gain = (np.convolve(wrapped, kernel / np.sqrt((kernel**2).sum()), "same")[len(kernel) : -len(kernel)])[
                :, None
            ]
        beams = np.exp(log_gain)
        noise = (floor + rain) * rays
        speckle_noise = self._speckle(rng, blurred.shape, NOISE_GRAIN)  # receiver noise: nearly white in range
        speckle_echo = ECHO_SPECKLE * self._speckle(rng, blurred.shape, conditions.speckle_grain) + 1.0 - ECHO_SPECKLE
        power = beams * (noise * speckle_noise + (blurred + streak) * speckle_echo) + self.mount * speckle_echo
        return (conditions.gain * cfg.gain * np.sqrt(power)).astype(np.float32)

    def to_cartesian(self, polar: np.ndarray) -> np.ndarray:
        """[A, R] grey levels -> [S, S] uint8 Cartesian scan (bilinear, wrapped at azimuth 0)."""
        padded = np.concatenate([polar[-1:], polar, polar[:1]])  # [A + 2, R]
        image = cv2.remap(
            padded, self._map_x, self._map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
        )
        return np.clip(np.rint(image), 0, 255).astype(np.uint8)
