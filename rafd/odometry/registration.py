"""Radar odometry: SE(2) motion between consecutive Cartesian scans by image registration (opencv + numpy FFT).

Method (one pair of the service's 512 px view: ~6-7 ms of one CPU core, a stream's first pair too; the figures per
CPU in docs/performance.md, "Odometry"):
1. Each scan is prepared at two levels (area-downsampled to at most COARSE_SIZE and FINE_SIZE pixels): the
   slowly varying background (noise floor, range attenuation) is removed by subtracting a wide blur, the
   rest is clipped at its 97th percentile and square-rooted so that bright (often moving) vehicles do not
   outvote the static scene, and a radial window centred on the radar hides the ego's near-range returns
   and fades the scan border. The window is rotation invariant about the radar: no bias on the yaw search.
2. Correlative yaw search (coarse): the previous scan is rotated about the radar by every yaw within
   +-PRIOR_YAW_WINDOW_DEG (1 degree steps) of the prior's yaw and cross-correlated with the current one by FFT
   (opencv's packed float32 DFT; each spectrum partly whitened once, the current scan's reused); the highest peak
   within MAX_STEP_M of zero shift wins, sub-step by a parabola. Without a prior (or with the best yaw on the
   window's edge) a narrower window is centred on the best of all +-MAX_YAW_DEG (WIDE_STEP_DEG steps), searched on
   the coarse level halved.
3. Refinement: ECC (Euclidean, inverse compositional: rafd.odometry.ecc) at the fine level from 2 improves the yaw;
   the shift is then read from the fine level's correlation at that yaw (ECC's least squares is pulled by moving
   objects, the correlation peak is not). ECC results that fail or move far from 2 are rejected (2's yaw stands).
   With refine=False the fine level is searched instead (+-0.5 degree).

A correlative search, not Fourier-Mellin: the polar magnitude spectra's peak drowns in speckle.

Conventions (geometry.py): pixel (u, v) with the radar at the image centre, metres x = (u - c) * res right,
y = (c - v) * res forward. The returned pose (x, y, yaw) is the CURRENT ego's pose in the PREVIOUS ego
frame: a static point seen at q_cur in the current frame is at R(yaw) q_cur + (x, y) in the previous one,
and compose_poses(previous_world_pose, relative) is the current world pose. In geometry's terms this is
relative_pose(current_world_pose, previous_world_pose) (relative_pose(a, b) maps a's frame into b's).

Accuracy: `rafd odometry SEQ_DIR... --evaluate`; the bound is tested in tests/rafd/odometry/test_registration.py.
On small crops (256 px) a pair whose static scene is only long lines along the road while nearby vehicles move with
the ego can lock onto the vehicles (aperture problem): use the full scan where it is available.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import logging
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from rafd.geometry import compose_poses
from rafd.odometry.ecc import EccTemplate, align

log = logging.getLogger(__name__)

FINE_SIZE = 384  # largest side of the fine level (pixels): sub-pixel registration here gives ~cm
COARSE_SIZE = 128  # largest side of the coarse rotation search level
MAX_YAW_DEG = 15.0  # largest yaw change searched between consecutive scans (60 deg/s at 4 Hz)
COARSE_STEP_DEG = 1.0
WIDE_STEP_DEG = 3.0  # the wide search's steps (+-MAX_YAW_DEG, a stream's first pair): it only centres the coarse one
FINE_STEP_DEG = 0.5
CLIP_PERCENTILE = 97.0  # structure image clipped here before the square root
CENTRE_MASK_M = 4.0  # metres around the radar hidden (ego vehicle returns, near-range leakage)
WHITENING = 0.5  # cross-power spectrum divided by |.|^this: 1 = phase correlation, 0 = plain correlation
MAX_STEP_M = 8.0  # largest ego translation between consecutive scans (32 m/s at 4 Hz): bounds the peak search
MAX_ECC_SHIFT_PX = 3.0  # ECC refinements further than this (fine pixels) from the search result are rejected
MAX_ECC_YAW_DEG = 1.0  # ... or turning further than this
ECC_ITERATIONS = 10  # fewer put the Oxford sample's mean yaw error past its 0.108 degree bar; more gain nothing
ECC_EPS = 1e-4
PRIOR_YAW_WINDOW_DEG = 4.0  # coarse yaw search around the prior's yaw (the yaw rate changes less per scan)
WIDE_YAW_WINDOW_DEG = 2.0  # ... around the wide search's best yaw (WIDE_STEP_DEG steps, sub-stepped)
# A de-skewed pair is registered again with its own motion when it turned or moved this much more than the velocity
# it was de-skewed with (the onset of a turn, a hard brake): the sweep's smear then changes visibly.
REDESKEW_YAW_DEG = 0.5
REDESKEW_SHIFT_M = 0.2
GAP_PERIODS = 1.5  # a pair further apart than this many scan periods starts without a prior


def _level_size(size: int, largest: int) -> int:
    """Side after area-downsampling by the smallest integer factor that brings `size` to <= `largest`."""
    factor = max(1, math.ceil(size / largest))
    return max(16, int(round(size / factor)))


def _radial_window(size: int, resolution: float) -> np.ndarray:
    """[n, n] float32: 0 at the radar, smooth rise to 1 beyond CENTRE_MASK_M, smooth fall to 0 at the edge
    of the inscribed disc. Rotation invariant about the radar, so it cannot bias the yaw search."""
    centre = (size - 1) / 2.0
    coords = np.arange(size, dtype=np.float64) - centre
    radius = np.hypot(coords[None, :], coords[:, None])  # [n, n] pixels
    outer = size / 2.0
    inner = CENTRE_MASK_M / resolution
    rise = np.clip((radius - inner) / max(inner, 1.0), 0.0, 1.0)
    fall = np.clip((outer - radius) / (0.2 * outer), 0.0, 1.0)
    window = (0.5 - 0.5 * np.cos(np.pi * rise)) * (0.5 - 0.5 * np.cos(np.pi * fall))
    return window.astype(np.float32)


def _percentile_of_nonnegative(image: np.ndarray, q: float) -> float:
    """np.percentile(image, q) (linear interpolation) of an image >= 0, partitioning only its positive pixels: after
    the background is removed most pixels are 0."""
    flat = image.reshape(-1)
    positive = flat[flat > 0]
    zeros = flat.size - positive.size
    rank = q / 100.0 * (flat.size - 1)
    low = int(math.floor(rank))
    ranks = (low, min(low + 1, flat.size - 1))  # in the sorted image; those below `zeros` are 0
    wanted = sorted({k - zeros for k in ranks if k >= zeros})
    ordered = np.partition(positive, wanted) if wanted else positive
    below, above = (float(ordered[k - zeros]) if k >= zeros else 0.0 for k in ranks)
    return below + (above - below) * (rank - low)


class _Level:
    """One registration level: working size, metres per working pixel, its radial window (cached per geometry)."""

    _cache: dict[tuple[int, int, float], _Level] = {}

    def __init__(self, size: int, work: int, resolution: float) -> None:
        self.work = work
        self.resolution = resolution * size / work  # metres per working pixel
        self.window = _radial_window(work, self.resolution)

    @classmethod
    def get(cls, size: int, largest: int, resolution: float) -> _Level:
        key = (size, _level_size(size, largest), float(resolution))
        if key not in cls._cache:
            cls._cache[key] = cls(size, key[1], resolution)
        return cls._cache[key]

    def prepare(self, image: np.ndarray) -> np.ndarray:
        """[S, S] scan -> [n, n] float32 structure image (background removed, radial window applied)."""
        img: np.ndarray = np.asarray(image, dtype=np.float32)
        if img.shape[0] != self.work:
            img = cv2.resize(img, (self.work, self.work), interpolation=cv2.INTER_AREA)
        img = cv2.GaussianBlur(img, (0, 0), 0.8)
        background = cv2.GaussianBlur(img, (0, 0), 6.0)
        # Compress the dynamic range (clip at the 97th percentile, square root): bright, often moving,
        # vehicles must not outvote the static scene.
        img = np.maximum(img - background, 0.0)
        img = np.sqrt(np.minimum(img, _percentile_of_nonnegative(img, CLIP_PERCENTILE)))
        return img * self.window


def _rotation_warp(yaw: float, centre: float) -> np.ndarray:
    """2x3 pixel warp W with image_cur(u) = image_prev(W u) for a pure ego rotation `yaw` about the radar."""
    c, s = math.cos(yaw), math.sin(yaw)
    # [A | b] with A = R(-yaw) in pixel coordinates (image v points down) and b = (centre, centre) - A (centre, centre);
    # written out: the search builds one per candidate yaw
    return np.array([[c, s, centre - (c + s) * centre], [-s, c, centre - (c - s) * centre]], np.float32)


def pose_to_warp(pose: np.ndarray, size: int, resolution: float) -> np.ndarray:
    """Relative pose (current ego in previous frame) -> 2x3 warp W (cv2 pixel indices) with
    current(u) = previous(W u), i.e. cv2.warpAffine(previous, W, flags=WARP_INVERSE_MAP) predicts current."""
    centre = (size - 1) / 2.0
    warp = _rotation_warp(float(pose[2]), centre)
    warp[:, 2] += np.array([pose[0] / resolution, -pose[1] / resolution], dtype=np.float32)
    return warp


def warp_to_pose(warp: np.ndarray, size: int, resolution: float) -> np.ndarray:
    """Inverse of pose_to_warp (the rotation part is re-orthogonalised through its angle)."""
    warp = np.asarray(warp, dtype=np.float64)
    yaw = math.atan2(warp[0, 1], warp[0, 0])
    centre = (size - 1) / 2.0
    base = _rotation_warp(yaw, centre).astype(np.float64)
    shift = warp[:, 2] - base[:, 2]
    return np.array([shift[0] * resolution, -shift[1] * resolution, yaw])


def _rotated(image: np.ndarray, yaw: float) -> np.ndarray:
    """The previous scan as it would look after a pure ego rotation `yaw` about the radar."""
    size = image.shape[0]
    return cv2.warpAffine(
        image, _rotation_warp(yaw, (size - 1) / 2.0), (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    )


@functools.lru_cache(maxsize=16)
def _shift_offsets(size: int, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """([n] signed shift of each index of a wrapped correlation surface, [m, m] mask of shifts <= radius over the
    indices `near`, [m] the indices whose shift is within radius along one axis); cached."""
    offsets = np.fft.fftfreq(size, 1.0 / size)
    near = np.flatnonzero(np.abs(offsets) <= radius)
    allowed = np.hypot(offsets[near][None, :], offsets[near][:, None]) <= radius
    offsets.flags.writeable = allowed.flags.writeable = near.flags.writeable = False  # shared through the cache
    return offsets, allowed, near


def _vertex(left: float, mid: float, right: float) -> float:
    """Sub-sample offset in [-0.5, 0.5] of the maximum of the parabola through three samples."""
    curvature = left - 2.0 * mid + right
    return float(np.clip(0.5 * (left - right) / curvature, -0.5, 0.5)) if curvature < 0 else 0.0


def _peak_vertex(left: float, mid: float, right: float) -> float:
    """Sub-pixel offset of a correlation peak: a Gaussian through three positive samples (less biased towards
    whole pixels than a parabola), else the parabola."""
    if min(left, mid, right) > 0:
        return _vertex(math.log(left), math.log(mid), math.log(right))
    return _vertex(left, mid, right)


def _whitened_spectrum(image: np.ndarray) -> np.ndarray:
    """[n, n] real image -> [n, n] float32 its 2-D DFT in opencv's packed (CCS) form, each coefficient divided by
    |.|^WHITENING. Whitening each spectrum on its own is the whitening of their product (|a b|^w = |a|^w |b|^w), so a
    scan's spectrum is whitened once and reused by every search it takes part in."""
    spectrum = cv2.dft(np.asarray(image, np.float32))  # [n, n] CCS
    n = spectrum.shape[0]
    power = cv2.mulSpectrums(spectrum, spectrum, 0, conjB=True)  # |X|^2 in each coefficient's real slot, 0 in its imag
    scale = np.sqrt(np.sqrt(power)) if WHITENING == 0.5 else power ** (0.5 * WHITENING)  # a fifth of cv2.pow
    # each imaginary slot takes its coefficient's magnitude from the real slot before it: columns 1.. of every row are
    # (re, im) pairs, as are rows 1.. of column 0 (and of the last column for even n, whose last slot is real)
    pairs = n if n % 2 else n - 1
    scale[:, 2:pairs:2] = scale[:, 1:pairs:2]
    for column in (0, n - 1) if n % 2 == 0 else (0,):
        scale[2:pairs:2, column] = scale[1:pairs:2, column]
    scale += 1e-9
    return spectrum / scale


@dataclass(eq=False)
class Plane:
    """One level of one scan: its structure image, with the whitened spectrum and the halved copy the searches take
    from it made once (a scan is the current one of one pair and the previous one of the next)."""

    image: np.ndarray  # [n, n] float32 structure image (_Level.prepare), never written in place
    # made on first use, without a lock: two threads that race compute the same array, and Python 3.11's
    # functools.cached_property would hold one lock for every Plane of the process while it computes
    _spectrum: np.ndarray | None = field(default=None, init=False, repr=False)
    _halved: Plane | None = field(default=None, init=False, repr=False)

    @property
    def spectrum(self) -> np.ndarray:
        if self._spectrum is None:
            self._spectrum = _whitened_spectrum(self.image)
        return self._spectrum

    @property
    def halved(self) -> Plane:
        if self._halved is None:
            side = self.image.shape[0] // 2
            self._halved = Plane(cv2.resize(self.image, (side, side), interpolation=cv2.INTER_AREA))
        return self._halved


@dataclass(eq=False)
class Levels:
    """A scan's two registration levels."""

    coarse: Plane
    fine: Plane


def _search_rotation(
    previous: np.ndarray, current: Plane, yaws: np.ndarray, max_shift_px: float
) -> tuple[float, tuple[float, float], float]:
    """Correlative search: rotate `previous` by each candidate yaw, cross-correlate with `current` (FFT, partly
    whitened), keep the highest peak within `max_shift_px` of zero shift; sub-step yaw and shift by parabolas
    through the neighbours. -> (yaw, shift (x, y) with current(u) ~ rotated_previous(u - shift), score)."""
    n = previous.shape[0]
    # The peak is searched only among shifts within max_shift_px: the wrapped surface's four corners, not all n^2.
    offsets, allowed, near = _shift_offsets(n, max_shift_px)
    scores: list[float] = []
    best, peak_best = 0, 0  # the best yaw's index and peak so far, and its surface:
    surface: np.ndarray = np.zeros((0, 0), np.float32)
    for index, yaw in enumerate(yaws):
        cross = cv2.mulSpectrums(current.spectrum, _whitened_spectrum(_rotated(previous, float(yaw))), 0, conjB=True)
        correlation = cv2.idft(cross, flags=cv2.DFT_REAL_OUTPUT | cv2.DFT_SCALE)  # [n, n] wrapped correlation
        masked = np.where(allowed, correlation[near[:, None], near[None, :]], -np.inf)  # [m, m]
        peak = int(np.argmax(masked))
        scores.append(float(masked.flat[peak]))
        if index == 0 or scores[-1] > scores[best]:
            best, peak_best, surface = index, peak, correlation
    yaw = float(yaws[best])
    if 0 < best < len(yaws) - 1:
        yaw += _vertex(*scores[best - 1 : best + 2]) * float(yaws[1] - yaws[0])
    row_in, col_in = divmod(peak_best, len(near))
    row, col = int(near[row_in]), int(near[col_in])
    dx = _peak_vertex(surface[row, (col - 1) % n], surface[row, col], surface[row, (col + 1) % n])
    dy = _peak_vertex(surface[(row - 1) % n, col], surface[row, col], surface[(row + 1) % n, col])
    return yaw, (float(offsets[col] + dx), float(offsets[row] + dy)), scores[best]


def _wide_yaw(previous: Plane, current: Plane, resolution: float) -> float:
    """The best yaw in all of +-MAX_YAW_DEG, searched on the coarse level halved (a quarter of its pixels): only the
    centre of the windowed search at the coarse level (a stream's first pair, or a yaw on the prior window's edge)."""
    yaws = np.deg2rad(np.arange(-MAX_YAW_DEG, MAX_YAW_DEG + 1e-9, WIDE_STEP_DEG))
    yaw, _, _ = _search_rotation(previous.halved.image, current.halved, yaws, MAX_STEP_M / (2.0 * resolution))
    return yaw


def _window(half_width_deg: float) -> np.ndarray:
    """[K] yaw offsets (radians) of the coarse search: +-half_width_deg in COARSE_STEP_DEG steps."""
    return np.deg2rad(np.arange(-half_width_deg, half_width_deg + 1e-9, COARSE_STEP_DEG))


def _shift_to_warp(yaw: float, shift: tuple[float, float], size: int) -> np.ndarray:
    """Rotation `yaw` + correlation shift s -> 2x3 warp W with current(u) = previous(W u): the search's s means
    current(u) ~ rotated_prev(u - s) = previous(A (u - s) + b) with [A | b] the rotation warp."""
    warp = _rotation_warp(yaw, (size - 1) / 2.0).astype(np.float64)
    warp[:, 2] -= warp[:, :2] @ np.asarray(shift, dtype=np.float64)
    return warp.astype(np.float32)


def _refine_yaw(previous: np.ndarray, current: np.ndarray, warp: np.ndarray) -> float | None:
    """ECC (Euclidean, inverse compositional: rafd.odometry.ecc) from `warp` -> refined yaw, or None when ECC fails or
    strays."""
    size = previous.shape[0]
    start = warp_to_pose(warp, size, 1.0)  # (x px, y px, yaw)
    template = EccTemplate.of(current)
    aligned = None if template is None else align(template, previous, warp, ECC_ITERATIONS, ECC_EPS)
    if aligned is None:  # no structure, or no convergence from this start: keep the correlation estimate
        log.debug("ECC refinement failed; keeping the correlation estimate")
        return None
    warp = aligned[0]
    moved = warp_to_pose(warp, size, 1.0) - start
    if (
        not np.all(np.isfinite(moved))
        or np.hypot(moved[0], moved[1]) > MAX_ECC_SHIFT_PX
        or abs(moved[2]) > np.deg2rad(MAX_ECC_YAW_DEG)
    ):
        log.debug("ECC refinement moved (%.2f px, %.2f px, %.3f rad) from the estimate; rejected", *moved)
        return None
    return float(moved[2] + start[2])


# ---------------------------------------------------------------- the sweep's timing and de-skewing
@dataclass(frozen=True)
class SweepTiming:
    """When each azimuth of a scan was measured, relative to the time the scan's pose refers to.

    A Navtech scan is one clockwise sweep from straight ahead: azimuth theta (radians clockwise from forward) is
    measured `reference_fraction` sweeps before ... after the scan's reference time. Native scans (Oxford, Boreas)
    carry every azimuth's timestamp (`azimuths`, `seconds`: from the first azimuth) and refer to their first azimuth;
    RADIATE-format scans carry none: a uniform sweep over the period between scans is assumed, referred to its middle
    (the simulator's convention; RADIATE does not document where in the sweep its timestamps fall).
    """

    period_s: float  # one rotation
    reference_fraction: float = 0.5  # where in the sweep the scan's timestamp (and pose) lies: 0 start, 0.5 middle
    azimuths: np.ndarray | None = None  # [A] radians clockwise from forward, increasing (native scans)
    seconds: np.ndarray | None = None  # [A] seconds from the first azimuth (native scans)
    # a native scan's per-pixel offsets per level geometry (_SweepGrid.offsets): its scan is de-skewed up to 4 times
    pixel_offsets: dict[tuple[int, float], np.ndarray] = field(default_factory=dict, compare=False, repr=False)

    @classmethod
    def of_native(cls, timestamps_us: np.ndarray, azimuths: np.ndarray) -> SweepTiming:
        """A native scan's own timing (rafd.scans.native.NativeScan.timestamps_us / .azimuths), referred to its first
        azimuth (the time the datasets name the scan by)."""
        seconds = (np.asarray(timestamps_us, np.int64) - int(timestamps_us[0])) * 1e-6
        azimuths = np.asarray(azimuths, np.float64)
        step = (seconds[-1] - seconds[0]) / max(1, len(seconds) - 1)
        return cls(float(seconds[-1] + step), 0.0, azimuths, seconds)

    def offsets(self, theta: np.ndarray) -> np.ndarray:
        """Azimuths theta [...] (radians clockwise from forward, in [0, 2 pi)) -> seconds after the reference time."""
        if self.azimuths is None or self.seconds is None:
            return (theta / (2.0 * np.pi) - self.reference_fraction) * self.period_s
        # an azimuth before the first measured one (the seam) is measured at the very end of the sweep
        turn = np.where(theta < self.azimuths[0], theta + 2.0 * np.pi, theta)
        azimuths = np.append(self.azimuths, self.azimuths[0] + 2.0 * np.pi)
        seconds = np.append(self.seconds, self.period_s)
        return np.interp(turn, azimuths, seconds) - self.reference_fraction * self.period_s


class _SweepGrid:
    """Per working pixel of a level: metres (x right, y forward), azimuth clockwise from forward and its fraction of
    the sweep (cached per geometry: the de-skew is a few multiply-adds per pixel)."""

    _cache: dict[tuple[int, float], _SweepGrid] = {}

    def __init__(self, size: int, resolution: float) -> None:
        centre = (size - 1) / 2.0
        coords = (np.arange(size, dtype=np.float32) - centre) * resolution
        self.x, self.y = np.meshgrid(coords, -coords, indexing="xy")  # [n, n] metres, float32
        self.theta = np.mod(np.arctan2(self.x, self.y), 2.0 * np.pi)  # [n, n] clockwise from forward
        self.turn = self.theta / (2.0 * np.pi)  # [n, n] fraction of the sweep
        self.centre, self.resolution = centre, resolution

    @classmethod
    def get(cls, size: int, resolution: float) -> _SweepGrid:
        key = (size, float(resolution))
        if key not in cls._cache:
            cls._cache[key] = cls(size, resolution)
        return cls._cache[key]

    def offsets(self, timing: SweepTiming) -> np.ndarray:
        """[n, n] seconds after the reference at which each pixel's azimuth was measured."""
        if timing.azimuths is None:  # uniform: SweepTiming.offsets, one multiply-add (no cache per stream's period)
            return (self.turn - timing.reference_fraction) * timing.period_s
        key = (self.theta.shape[0], self.resolution)
        if key not in timing.pixel_offsets:  # a native scan's own timestamps: kept with the scan's timing
            timing.pixel_offsets[key] = timing.offsets(self.theta).astype(np.float32)
        return timing.pixel_offsets[key]


def deskew(image: np.ndarray, resolution: float, velocity: np.ndarray, timing: SweepTiming) -> np.ndarray:
    """Undo the ego motion during the sweep: [n, n] level image -> the scene as seen from the pose at the reference
    time. `velocity` (vx, vy m/s in the ego frame, yaw rate rad/s) is taken constant over the sweep: a point measured
    tau seconds after the reference, at q in the sensor frame of that moment, lies at R(w tau) q + v tau in the
    reference frame, so the de-skewed image at p samples the scan at q = R(-w tau)(p - v tau), tau read at p's azimuth
    (q's differs by the motion over the sweep seen from the point: a fraction of a degree beyond a few metres)."""
    grid = _SweepGrid.get(image.shape[0], resolution)
    vx, vy, w = (float(v) for v in velocity)
    tau = grid.offsets(timing)
    angle = -w * tau
    c, s = np.cos(angle), np.sin(angle)
    p_x, p_y = grid.x - vx * tau, grid.y - vy * tau
    map_x = (c * p_x - s * p_y) / resolution + grid.centre
    map_y = grid.centre - (s * p_x + c * p_y) / resolution
    return cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


# ---------------------------------------------------------------- one stream's odometry
@dataclass
class PreparedScan:
    """One scan's registration levels, prepared once and reused as the next pair's previous scan."""

    raw: Levels  # as scanned
    size: int  # side of the scan it was made from
    timing: SweepTiming | None = None
    velocity: np.ndarray | None = None  # the motion its de-skewed levels undo (m/s, m/s, rad/s)
    deskewed: Levels | None = None  # with `velocity` undone


class Odometer:
    """Radar odometry between consecutive scans of one stream, motion-compensated.

    prepare() makes a scan's registration levels once; estimate(previous, current, dt, prior) registers a pair. With
    sweep timings, each scan is de-skewed (`deskew`) with its ego velocity before registering: the
    velocity comes from the prior (the previous pair's motion: constant velocity) and is re-estimated from the pair's
    own registration, then the pair is registered again de-skewed, so the pose refers to the scans' reference times
    and turns no longer smear the scans. Without a prior (a stream's first pair) the raw scans are registered, and
    that motion de-skews the current scan for the next pair.
    """

    def __init__(self, resolution: float, refine: bool = True) -> None:
        if not (math.isfinite(resolution) and resolution > 0):
            raise ValueError(f"resolution must be a positive number of metres per pixel, got {resolution}")
        self.resolution = resolution
        self.refine = refine

    def _levels(self, size: int) -> tuple[_Level, _Level]:
        return _Level.get(size, COARSE_SIZE, self.resolution), _Level.get(size, FINE_SIZE, self.resolution)

    def prepare(self, image: np.ndarray, timing: SweepTiming | None = None) -> PreparedScan:
        """[S, S] scan (uint8 or float, radar at the centre) -> its levels."""
        image = np.asarray(image)
        if image.ndim != 2 or image.shape[0] != image.shape[1]:
            raise ValueError(f"odometry needs a square scan, got shape {image.shape}")
        coarse, fine = self._levels(int(image.shape[0]))
        return PreparedScan(
            Levels(Plane(coarse.prepare(image)), Plane(fine.prepare(image))), int(image.shape[0]), timing
        )

    def _deskewed(self, scan: PreparedScan, velocity: np.ndarray, keep: bool = False) -> Levels:
        """The scan's levels with `velocity` undone; `keep`: a scan already de-skewed keeps its own velocity's."""
        assert scan.timing is not None
        if keep and scan.deskewed is not None:
            return scan.deskewed
        if scan.deskewed is None or scan.velocity is None or not np.array_equal(scan.velocity, velocity):
            coarse, fine = self._levels(scan.size)
            scan.velocity = np.array(velocity, dtype=np.float64)
            scan.deskewed = Levels(
                Plane(deskew(scan.raw.coarse.image, coarse.resolution, velocity, scan.timing)),
                Plane(deskew(scan.raw.fine.image, fine.resolution, velocity, scan.timing)),
            )
        return scan.deskewed

    def search(
        self,
        previous: Levels,
        current: Levels,
        size: int,
        expected_yaw: float | None = None,
    ) -> np.ndarray | None:
        """The correlative search -> [3] pose, None for a blank scan. `expected_yaw` (the prior's) narrows the coarse
        yaw search to +-PRIOR_YAW_WINDOW_DEG around it; without one, or with the best yaw on that window's edge, the
        wide search over +-MAX_YAW_DEG centres a +-WIDE_YAW_WINDOW_DEG one. With `refine` the coarse level's pose is
        returned: finish's ECC starts from it (starting it from a fine-level shift at the coarse yaw left every error
        of the odometry's accuracy check unchanged at 0.3 of this stage's cost); without, the fine level is searched
        +-0.5 degree."""
        coarse, fine = self._levels(size)
        if not (previous.fine.image.any() and current.fine.image.any()):
            log.warning("odometry: a scan holds no structure (blank image); returning zero motion")
            return None
        reach = MAX_STEP_M / coarse.resolution
        on_edge = False
        if expected_yaw is not None:
            yaw, shift, _ = _search_rotation(
                previous.coarse.image, current.coarse, expected_yaw + _window(PRIOR_YAW_WINDOW_DEG), reach
            )
            on_edge = abs(yaw - expected_yaw) > np.deg2rad(PRIOR_YAW_WINDOW_DEG - COARSE_STEP_DEG)
        if expected_yaw is None or on_edge:  # no prior, or the best yaw on the window's edge: the wide search
            expected_yaw = _wide_yaw(previous.coarse, current.coarse, coarse.resolution)
            yaw, shift, _ = _search_rotation(
                previous.coarse.image, current.coarse, expected_yaw + _window(WIDE_YAW_WINDOW_DEG), reach
            )
        if self.refine:
            return warp_to_pose(_shift_to_warp(yaw, shift, coarse.work), coarse.work, coarse.resolution)
        steps = np.deg2rad(np.arange(-1, 2) * FINE_STEP_DEG)
        yaw, shift, _ = _search_rotation(previous.fine.image, current.fine, yaw + steps, MAX_STEP_M / fine.resolution)
        return warp_to_pose(_shift_to_warp(yaw, shift, fine.work), fine.work, fine.resolution)

    def finish(
        self,
        previous: Levels,
        current: Levels,
        size: int,
        pose: np.ndarray,
    ) -> np.ndarray:
        """A search's pose -> the final [3] pose: with `refine`, ECC improves the yaw; the shift is then read from the
        fine level's correlation at that yaw."""
        if not self.refine:
            return pose
        _, fine = self._levels(size)
        yaw = float(pose[2])
        refined = _refine_yaw(previous.fine.image, current.fine.image, pose_to_warp(pose, fine.work, fine.resolution))
        if refined is not None:
            yaw = refined
        _, shift, _ = _search_rotation(previous.fine.image, current.fine, np.array([yaw]), MAX_STEP_M / fine.resolution)
        return warp_to_pose(_shift_to_warp(yaw, shift, fine.work), fine.work, fine.resolution)

    def register(
        self,
        previous: Levels,
        current: Levels,
        size: int,
        expected_yaw: float | None = None,
    ) -> np.ndarray:
        """Levels of two scans -> [3] pose of the current ego in the previous ego frame (search, then finish)."""
        pose = self.search(previous, current, size, expected_yaw)
        return np.zeros(3) if pose is None else self.finish(previous, current, size, pose)

    def estimate(
        self, previous: PreparedScan, current: PreparedScan, dt: float | None = None, prior: np.ndarray | None = None
    ) -> np.ndarray:
        """[3] pose (x m, y m, yaw rad) of the current ego in the previous ego frame. With both scans' timings and the
        time between them `dt`, motion-compensated (the class docstring); `prior`: the previous pair's pose.

        Every registration is finished (ECC), the one a re-de-skew replaces too: the re-de-skew decision needs the
        refined pose. A re-de-skewed pair starts its ECC from the pose before it instead of searching again: the
        de-skew moves the scene by a fraction of ECC's reach."""
        if previous.size != current.size:
            raise ValueError(f"odometry needs two scans of the same size, got {previous.size} and {current.size}")
        compensate = previous.timing is not None and current.timing is not None and dt is not None and dt > 0
        if not compensate:
            return self.register(previous.raw, current.raw, current.size)
        assert dt is not None
        size = current.size
        if prior is None:
            # A stream's first pair: no motion is known to de-skew with. It is registered raw, and its motion de-skews
            # the current scan, which the next pair registers against.
            pose = self.register(previous.raw, current.raw, size)
            self._deskewed(current, pose / dt)
            return pose
        # Each scan is de-skewed once, with its own velocity: the current one with the prior's (constant velocity),
        # the previous one kept as it was de-skewed when it was the current one.
        used = np.asarray(prior, dtype=np.float64)
        previous_levels = self._deskewed(previous, used / dt, keep=True)
        current_levels = self._deskewed(current, used / dt)
        found = self.search(previous_levels, current_levels, size, float(used[2]))
        if found is None:
            return np.zeros(3)
        pose = self.finish(previous_levels, current_levels, size, found)
        change = pose - used
        if abs(np.rad2deg(change[2])) > REDESKEW_YAW_DEG or np.hypot(change[0], change[1]) > REDESKEW_SHIFT_M:
            # the motion changed within the pair (a turn begins, a hard brake): the current scan's own is the pair's
            current_levels = self._deskewed(current, pose / dt)
            pose = self.finish(previous_levels, current_levels, size, pose)
        return pose


def estimate_relative_pose(
    previous: np.ndarray,
    current: np.ndarray,
    resolution: float,
    refine: bool = True,
    timings: tuple[SweepTiming, SweepTiming] | None = None,
    dt: float | None = None,
) -> np.ndarray:
    """[S, S] previous and current scans (uint8 or float, radar at the centre, any square size) -> [3] pose
    (x m, y m, yaw rad) of the current ego in the previous ego frame. refine=False skips ECC (faster, ~2x the yaw
    error). With both scans' sweep timings and the time between them, motion-compensated (Odometer)."""
    previous, current = np.asarray(previous), np.asarray(current)
    if previous.ndim != 2 or previous.shape[0] != previous.shape[1] or previous.shape != current.shape:
        raise ValueError(f"odometry needs two square scans of the same size, got {previous.shape} and {current.shape}")
    odometer = Odometer(resolution, refine)
    prev_timing, cur_timing = timings if timings is not None else (None, None)
    return odometer.estimate(odometer.prepare(previous, prev_timing), odometer.prepare(current, cur_timing), dt)


class OdometryStream:
    """The odometry of one stream of scans: add() each scan in time order -> its pose in the previous scan's frame.

    Keeps the previous scan's prepared (and de-skewed) levels and the previous pair's motion as the next pair's prior,
    so each scan is prepared once and each pair registered once in the usual case (Odometer). Scans without a
    timestamp are registered raw; with timestamps, motion-compensated over a uniform sweep of the period between
    scans, or over the scan's own `timing` (native scans). After a gap longer than GAP_PERIODS periods the prior is
    dropped (the motion may have changed)."""

    def __init__(self, resolution: float, refine: bool = True) -> None:
        self.odometer = Odometer(resolution, refine)
        self.previous: PreparedScan | None = None
        self.previous_time: float | None = None
        self.prior: np.ndarray | None = None
        self.period: float | None = None  # typical time between scans, from the first pair on

    def fork(self) -> OdometryStream:
        """A copy whose add() leaves this one unchanged (the service commits a stream's odometry only together with
        the frame's answer: a frame that fails after its odometry must leave the stream as it was). Cheap: the
        prepared levels are shared, never written in place; the previous scan's record is copied because add()
        attaches its sweep timing and de-skewed levels to it."""
        forked = copy.copy(self)
        if self.previous is not None:
            forked.previous = dataclasses.replace(self.previous)
        return forked

    def add(
        self, image: np.ndarray, timestamp: float | None = None, timing: SweepTiming | None = None
    ) -> np.ndarray | None:
        """One scan -> [3] its ego pose in the previous scan's ego frame (None for the first scan)."""
        dt = None
        if timestamp is not None and self.previous_time is not None:
            dt = float(timestamp - self.previous_time)
            if dt <= 0:
                raise ValueError(f"scan timestamps must increase: {timestamp} after {self.previous_time}")
        gap = dt is not None and self.period is not None and dt > GAP_PERIODS * self.period
        if dt is not None and not gap:
            self.period = dt if self.period is None else self.period
        if timing is None and timestamp is not None and self.period is not None:
            timing = SweepTiming(self.period)
        current = self.odometer.prepare(image, timing)
        if self.previous is not None and self.previous.timing is None and timing is not None and self.period:
            self.previous.timing = SweepTiming(self.period)  # the first scan's sweep, known once a period is
        relative = None
        if self.previous is not None:
            relative = self.odometer.estimate(self.previous, current, dt, None if gap else self.prior)
            # a motion across a gap (seconds, not one period) is no prior for the next pair of consecutive scans
            self.prior = None if gap else relative
        self.previous, self.previous_time = current, timestamp
        return relative


def estimate_sequence_poses(
    images: Iterable[np.ndarray],
    resolution: float,
    timestamps: Sequence[float] | None = None,
    timings: Iterable[SweepTiming | None] | None = None,
) -> np.ndarray:
    """N scans (any iterable, consumed once: a generator keeps one pair in memory) -> [N, 3] world poses by
    chaining consecutive relative poses (OdometryStream); the first pose is (0, 0, 0). With the scans' `timestamps`
    (seconds) the motion is compensated (uniform sweeps over the period between scans unless `timings` give each
    scan's own)."""
    stream = OdometryStream(resolution)
    poses: list[np.ndarray] = []
    timing_iter = iter(timings) if timings is not None else None
    for index, image in enumerate(images):
        timing = next(timing_iter) if timing_iter is not None else None
        relative = stream.add(image, None if timestamps is None else float(timestamps[index]), timing)
        poses.append(np.zeros(3) if relative is None else compose_poses(poses[-1], relative))
    return np.array(poses, dtype=np.float64).reshape(-1, 3)
