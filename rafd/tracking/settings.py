"""The tracker's settings: one frozen dataclass, every default with its reason (docs/tracking.md has the figures)."""

from __future__ import annotations

from dataclasses import dataclass

# Where a box's velocity comes from (TrackerSettings.velocity), the four candidates measured side by side:
VELOCITY_MODES = (
    "flow_centre",  # (a) the flow sampled at the box centre / the pair's interval; no flow there: none
    "flow_box",  # (b) the flow over the box's cells weighted by their validity / the interval; no flow: none
    "filter",  # (c) a constant-velocity Kalman filter over the track's world positions only
    "filter_flow",  # (d) the same filter, seeded and updated by (b) as a velocity measurement
)
MATCHING = ("hungarian", "greedy")  # AB3DMOT's global assignment; CenterPoint's closest-first


@dataclass(frozen=True)
class TrackerSettings:
    velocity: str = "filter"  # the shipped model's flow is ~0 on vehicles: see docs/tracking.md
    matching: str = "hungarian"
    # Association: a detection may continue a track only within both gates of the track's predicted centre.
    gate_m: float = 4.0  # metres (Euclidean) from the predicted centre: 16 m/s for a new track's 0.25 s
    gate_sigmas: float = 5.0  # Mahalanobis gate in standard deviations of the predicted position (and box noise)
    class_gates_m: tuple[tuple[int, float], ...] = ()  # (class index, gate_m) overrides, CenterPoint-style
    # Life cycle.
    confirm_hits: int = 2  # detections a track needs before it is confirmed (a lone false positive never is)
    # A confirmed track lives on this many scans without a detection (2.5 s at 4 Hz; CenterPoint keeps 3 at 2 Hz):
    # the detector finds a vehicle in some scans and not others, and a track that outlives the gaps keeps its id.
    max_coast_frames: int = 10
    tentative_coast_frames: int = 2  # ... and a tentative one (0: it ends at its first miss)
    max_gap_s: float = 2.0  # a longer gap between scans ends every track (its prediction would be a guess)
    max_tracks: int = 256  # live tracks per stream (bounded state); coasting ones are evicted first
    # What is answered. Every answered detection carries its track; these choose which tracks are answered.
    answer_tentative: bool = True  # boxes of tracks not yet confirmed (False drops lone detections)
    answer_coasting: bool = False  # predicted boxes of confirmed tracks missed in this scan (no detection behind)
    answer_coast_frames: int = 3  # ... answered for at most this many missed scans (the track may live longer)
    coast_score_decay: float = 0.7  # a coasting box's score: its last detection's times this per missed scan
    # Constant-velocity Kalman filter in the world frame (state x, y, vx, vy).
    position_std_m: float = 0.6  # a detection centre's error per axis (0.55-0.57 m on simulated drives)
    acceleration_std: float = 0.5  # m/s^2 (per s^0.5), white-noise acceleration: a nearly constant velocity
    initial_speed_std: float = 8.0  # m/s, a new track's velocity prior without flow (town speeds up to ~15 m/s)
    # Parked or moving (filter modes): the answered velocity is the filter's times the probability that the track
    # moves at all (rafd.tracking.motion.moving_probability), its covariance the mixture's; None answers the
    # filter's velocity as it is. Most vehicles a town radar sees are parked, and a filter's noisy velocity for a
    # parked car is an error of its own.
    moving_prior: float | None = 0.5
    # The flow as a velocity measurement ("flow_box", "filter_flow"; "flow_centre" samples one point).
    flow_std_floor: float = 0.5  # m/s added in quadrature to the spread of the flow over the box
    flow_min_validity: float = 0.5  # mean validity of the cells behind a box's flow for it to be used
    flow_reach_fraction: float = 0.9  # |flow| at or beyond this share of its reach is saturated: not used

    def __post_init__(self) -> None:
        if self.velocity not in VELOCITY_MODES:
            raise ValueError(f"velocity must be one of {VELOCITY_MODES}, got {self.velocity!r}")
        if self.matching not in MATCHING:
            raise ValueError(f"matching must be one of {MATCHING}, got {self.matching!r}")
        positive = {
            "gate_m": self.gate_m,
            "gate_sigmas": self.gate_sigmas,
            "max_gap_s": self.max_gap_s,
            "position_std_m": self.position_std_m,
            "acceleration_std": self.acceleration_std,
            "initial_speed_std": self.initial_speed_std,
            "flow_std_floor": self.flow_std_floor,
            "flow_reach_fraction": self.flow_reach_fraction,
        }
        for name, value in positive.items():
            if not (value > 0 and value < float("inf")):
                raise ValueError(f"{name} must be a positive finite number, got {value}")
        if self.moving_prior is not None and not 0.0 < self.moving_prior < 1.0:
            raise ValueError(f"moving_prior must be in (0, 1) or None, got {self.moving_prior}")
        if self.confirm_hits < 1 or self.max_tracks < 1:
            raise ValueError("need confirm_hits >= 1 and max_tracks >= 1")
        if min(self.max_coast_frames, self.tentative_coast_frames, self.answer_coast_frames) < 0:
            raise ValueError("the coasting frame counts must be >= 0")
        if not 0.0 <= self.coast_score_decay <= 1.0 or not 0.0 <= self.flow_min_validity <= 1.0:
            raise ValueError("need coast_score_decay and flow_min_validity in [0, 1]")
        for _, gate in self.class_gates_m:
            if not (gate > 0 and gate < float("inf")):
                raise ValueError(f"class_gates_m holds a gate that is not a positive finite number: {gate}")

    @property
    def uses_flow(self) -> bool:
        return self.velocity != "filter"

    def gate_for(self, label: int) -> float:
        """The Euclidean gate (m) of a class index."""
        return dict(self.class_gates_m).get(int(label), self.gate_m)
