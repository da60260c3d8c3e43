"""A stream's tracks as one immutable value: arrays of every live track (struct of arrays), the id counter and the
last scan's time. step() never modifies a state; it builds the next one, so a caller can step a copy and keep the
old state until the whole request has succeeded (and a replayed frame steps the same old state again)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

STATUS_NAMES = ("tentative", "confirmed", "coasting")  # TrackedBoxes.status codes
TENTATIVE, CONFIRMED, COASTING = 0, 1, 2
VELOCITY_SOURCES = ("none", "flow", "track")  # TrackedBoxes.velocity_source codes
SOURCE_NONE, SOURCE_FLOW, SOURCE_TRACK = 0, 1, 2


def read_only(array: np.ndarray) -> np.ndarray:
    """A read-only view: the state's arrays cannot be changed through the state (step() builds every array it
    hands a state afresh, so no other reference to them is left writable)."""
    view = array.view()
    view.flags.writeable = False
    return view


@dataclass(frozen=True)
class TrackerState:
    """Every live track of one stream, row k = one track. World frame: the poses' fixed frame, float64."""

    ids: np.ndarray  # [N] int64, from next_id, never reused within the stream
    mean: np.ndarray  # [N, 4] world (x, y, vx, vy) metres, m/s
    covariance: np.ndarray  # [N, 4, 4]
    size: np.ndarray  # [N, 2] (width, length) metres of the last detection
    yaw: np.ndarray  # [N] world yaw of the last detection (ego yaw + pose yaw)
    score: np.ndarray  # [N] last detection's score
    label: np.ndarray  # [N] int64 class index
    age: np.ndarray  # [N] int64 scans since the track began (1 on its first)
    hits: np.ndarray  # [N] int64 scans with a detection
    misses: np.ndarray  # [N] int64 consecutive scans without one (0: seen in the last scan)
    evidence: np.ndarray  # [N] int8 what its velocity rests on: SOURCE_NONE / SOURCE_FLOW / SOURCE_TRACK
    next_id: int = 1
    timestamp: float | None = None  # the last scan stepped (seconds); None before the first
    scans: int = 0  # scans stepped

    def __post_init__(self) -> None:
        for name in TRACK_ARRAYS:
            value = getattr(self, name)
            if value.flags.writeable:
                object.__setattr__(self, name, read_only(value))

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def nbytes(self) -> int:
        """Bytes its arrays hold (at most max_tracks tracks: bounded)."""
        return sum(getattr(self, name).nbytes for name in TRACK_ARRAYS)

    @classmethod
    def empty(cls, first_id: int = 1) -> TrackerState:
        """A new stream's state; its first track gets `first_id`."""
        return cls(
            ids=np.zeros(0, np.int64),
            mean=np.zeros((0, 4)),
            covariance=np.zeros((0, 4, 4)),
            size=np.zeros((0, 2)),
            yaw=np.zeros(0),
            score=np.zeros(0),
            label=np.zeros(0, np.int64),
            age=np.zeros(0, np.int64),
            hits=np.zeros(0, np.int64),
            misses=np.zeros(0, np.int64),
            evidence=np.zeros(0, np.int8),
            next_id=int(first_id),
        )

    def take(self, rows: np.ndarray) -> TrackerState:
        """The state of only the tracks at `rows` (indices or a bool mask); counters kept."""
        return replace(self, **{name: getattr(self, name)[rows] for name in TRACK_ARRAYS})


TRACK_ARRAYS = ("ids", "mean", "covariance", "size", "yaw", "score", "label", "age", "hits", "misses", "evidence")


def concatenate(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Several groups of track rows (dicts of the same TRACK_ARRAYS names) -> one dict, the groups in that order."""
    return {name: np.concatenate([part[name] for part in parts]) for name in parts[0]}


def rows_of(state: TrackerState) -> dict[str, np.ndarray]:
    """A state's track arrays as a dict (read-only views)."""
    return {name: getattr(state, name) for name in TRACK_ARRAYS}
