"""Request and response models of the HTTP API.

Answers are built as these models: the OpenAPI document is generated from them, and the tests validate real answers
against them with unknown fields forbidden (`Answer`), so an answer cannot grow a field the schema does not declare.
On the hot path /detect's answer is built without validation (service.pipeline.detector, `model_construct`: its flow
arrays stay numpy arrays) and orjson writes it (`DetectResponse.to_json`).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import orjson
from pydantic import BaseModel, ConfigDict, Field

# The stream-id rule is defined once, in rafd.protocol, which the clients name their streams by too (URL-path-safe,
# printable, no whitespace, neither "." nor ".."); re-exported (`as`) for the routers' path and header parameters.
from rafd.protocol import STREAM_ID_MAX_LENGTH as STREAM_ID_MAX_LENGTH
from rafd.protocol import STREAM_ID_PATTERN as STREAM_ID_PATTERN
from rafd.protocol import STREAM_ID_RULE

StreamId = Annotated[
    str,
    Field(min_length=1, max_length=STREAM_ID_MAX_LENGTH, pattern=STREAM_ID_PATTERN, description=STREAM_ID_RULE),
]

# Physical ranges (422 `validation_error` beyond, the bound named): timestamps are seconds since the UNIX epoch from
# 0 (1970; small values such as 1, 2, 3 are fine: time since a sensor started) to 2100-01-01; poses are metres within
# 1e8 of the world origin (UTM northings reach 1e7, Earth-centred coordinates 6.4e6) and yaws within 1e4 rad
# (unwrapped: 1591 turns), where float64 still resolves a millimetre and a sine means something.
MAX_TIMESTAMP_S = 4_102_444_800.0
# A native scan's range bin (range_resolution_m): scanning radars' bins are centimetres (Navtech: 0.0432-0.0596 m);
# the bounds leave a wide margin either side while refusing a zero, a negative or a unit mistake of a thousand.
MIN_RANGE_BIN_M = 0.001
MAX_RANGE_BIN_M = 1.0
MAX_POSE_M = 1e8
MAX_YAW_RAD = 1e4
Timestamp = Annotated[
    float,
    Field(
        ge=0.0,
        le=MAX_TIMESTAMP_S,
        description="seconds since the UNIX epoch (or since the sensor started), 0 to 4102444800 (2100-01-01)",
    ),
]

RangeBin = Annotated[float, Field(ge=MIN_RANGE_BIN_M, le=MAX_RANGE_BIN_M, description="metres per range bin")]

# No coercion: a JSON timestamp is a number (an integer is a number), never "1.5" or true.
Strict = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True)


class Pose(BaseModel):
    """World pose of the radar's ego frame: world = R(yaw) @ ego + (x, y)."""

    model_config = Strict
    x: float = Field(ge=-MAX_POSE_M, le=MAX_POSE_M, description="metres, within 1e8 of the world origin")
    y: float = Field(ge=-MAX_POSE_M, le=MAX_POSE_M, description="metres, within 1e8 of the world origin")
    yaw: float = Field(ge=-MAX_YAW_RAD, le=MAX_YAW_RAD, description="radians, counter-clockwise, within 1e4")


class DetectBody(BaseModel):
    """The non-image fields of POST /detect as posted (JSON body or multipart form)."""

    model_config = Strict
    stream_id: StreamId | None = Field(
        default=None,
        description="required unless the X-Stream-Id header or the path names the stream; "
        "must equal them when both are given",
    )
    timestamp: Timestamp = Field(
        description="seconds since the UNIX epoch (or since the sensor started), 0 to 4102444800 (2100-01-01); must "
        "increase within a stream, by at least RAFD_MIN_FRAME_GAP_S"
    )
    pose: Pose | None = Field(default=None, description="omit to estimate ego motion from the radar (odometry)")
    previous_timestamp: Timestamp | None = Field(
        default=None,
        description="optional: the timestamp of this stream's previous frame that the client got an answer (200) for; "
        "a replica whose last accepted frame of the stream is another one restarts the stream's buffer "
        '(stream_restarted: "previous_timestamp_mismatch") instead of continuing a chain that is not the client\'s. '
        "Must be before timestamp; omit on a stream's first frame",
    )
    range_resolution_m: RangeBin | None = Field(
        default=None,
        description="native scans only: metres per range bin, as the sensor reports it (e.g. a ROS 2 bag's "
        "RadarConfigurationMsg); replaces the bin size of the dataset the scan's shape names (GET /model "
        "accepted_native.format_rule). 0.001 to 1",
    )


class DetectJson(DetectBody):
    image: str = Field(
        min_length=1,
        description="base64 PNG, 8-bit greyscale, no line breaks (a data:image/png;base64, prefix is accepted)",
    )


class DetectFields(DetectBody):
    """One frame's fields once the stream id is resolved from the body, the X-Stream-Id header or the path."""

    stream_id: StreamId


class Answer(BaseModel):
    """Base of every answer model: unknown fields are an error when an answer is validated against it."""

    model_config = ConfigDict(extra="forbid", populate_by_name=True)


class TrackOut(Answer):
    status: Literal["tentative", "confirmed", "coasting"] = Field(
        description="tentative until the track is detected in 2 scans; coasting: a confirmed track not detected in "
        "this scan, its box predicted (answered only with RAFD_TRACKS_ANSWER_COASTING)"
    )
    age: int = Field(description="scans since the track began (1 on its first)")
    hits: int = Field(description="scans in which it was detected")


class Velocity(Answer):
    x: float
    y: float


class BoxOut(Answer):
    x: float = Field(description="centre, metres right of the radar (ego frame of this frame)")
    y: float = Field(description="centre, metres forward of the radar")
    width: float = Field(description="metres along the box's x axis")
    length: float = Field(description="metres along the box's y axis")
    yaw: float = Field(description="radians, counter-clockwise from ego x")
    score: float
    class_id: int
    class_name: str = Field(alias="class")
    polygon: list[list[float]] = Field(description="4 corners (u, v) in the POSTED image's pixels")
    track_id: str = Field(
        description="the box's track (rafd.tracking): the same while the vehicle is seen, never reused within a "
        "stream; CHAIN-N, where CHAIN is new with each chain of the stream (a restart, a failover), so ids of "
        "another chain never equal these"
    )
    track: TrackOut
    velocity: Velocity | None = Field(
        description="ground velocity (ego motion removed), m/s in this frame's ego axes (x right, y forward); null "
        "when nothing measured it yet (velocity_source none: a track's first scan)"
    )
    velocity_covariance: list[list[float]] | None = Field(
        description="the velocity's 2x2 covariance, (m/s)^2, in the same axes; null with the velocity"
    )
    velocity_source: Literal["flow", "track", "none"] = Field(
        description="what the velocity rests on: track (the track's constant-velocity filter over its positions), "
        "flow (the model's flow), none"
    )


class FlowGrid(Answer):
    height: int
    width: int
    cell_size_m: float
    stride_px: int = Field(description="model-input pixels per cell")
    origin_px: list[int] = Field(description="(u, v) of cell (0, 0)'s top-left corner in the POSTED image")
    cell_centre_rule: str


class FlowOut(Answer):
    pair: list[float | None] = Field(description="timestamps (previous, newest) of the frame pair the flow is for")
    shape: list[int] = Field(description="[2, Hf, Wf]")
    units: Literal["m"] = "m"
    axes: str
    grid: FlowGrid
    encoding: Literal["list", "base64-float16", "png"]
    values: list[list[list[float]]] | str
    validity: list[list[float]] | str = Field(
        description="[Hf, Wf] in [0, 1], in `encoding` like `values`: where the flow was measured (1 = over the "
        "network's whole search range, 0 = not at all: outside the previous frame's crop or at the crop's edge), "
        "rounded down to 0.01"
    )
    validity_min: float = Field(description="cells with validity at or above this are valid (rafd.flow_validity)")
    search_reach_m: float = Field(description="metres the flow's search reaches from a cell (validity 1)")


class CoveredOut(Answer):
    side_px: int = Field(description="side of the square detected over, centred on the radar, in posted pixels")
    offset_px: int = Field(description="posted pixel (u and v) of that square's top-left corner")
    side_m: float = Field(description="its side in metres")
    range_m: float | None = Field(
        description="boxes farther than this from the radar are not answered (RAFD_DETECT_RANGE_M); null: the "
        "whole scan"
    )
    tiles: int = Field(description="the model's inputs stepped over it (one for a scan of the model's size)")


class InputOut(Answer):
    posted_size: int
    model_size: int
    posted_format: Literal["cartesian", "polar", "native"] = Field(
        description="polar: a Navtech_Polar scan was posted, native: an Oxford / Boreas native scan; either is "
        "converted to RADIATE's Cartesian scan, and posted_size, covered and every polygon are in that Cartesian "
        "scan's pixels"
    )
    covered: CoveredOut = Field(
        description="what was detected over: the whole scan, or within RAFD_DETECT_RANGE_M of the radar"
    )
    native_format: str | None = Field(
        default=None,
        description="native scans: the format they were read as (oxford, boreas, boreas-2021, boreas-rt: GET /model "
        "accepted_native); left out for other scans",
    )
    native_range_bin_m: float | None = Field(
        default=None,
        description="native scans: the metres per range bin used (the request's range_resolution_m, else the "
        "format's); left out for other scans",
    )


class TimingOut(Answer):
    read_ms: float = Field(description="from arrival until the body is read, parsed and placed in its stream")
    decode_ms: float = Field(description="the image: decode queue, base64 and PNG decoding, crop")
    odometry_ms: float
    wait_ms: float = Field(description="time queued behind earlier frames of the same stream")
    model_ms: float
    post_ms: float
    total_ms: float


class ModelRef(Answer):
    version: str
    checkpoint_sha256: str
    runtime: str = Field(description="the runtime that computed the answer: onnxruntime or openvino")
    precision: str = Field(description="what it computed in: fp32, bf16 or int8 (the quantized MODEL.int8.onnx)")


# evicted / expired: the store ended the previous chain; gap / previous_timestamp_mismatch / view_changed: the frame
# itself showed that the chain held here is not its own (service/pipeline/detector.py, `chain_break`), and it starts
# a new one.
RestartReason = Literal["evicted", "expired", "gap", "previous_timestamp_mismatch", "view_changed"]


class DetectResponse(Answer):
    stream_id: str
    timestamp: float
    frames_used: int
    num_frames: int
    warming_up: bool = Field(description="true while fewer than num_frames frames are buffered")
    stream_restarted: RestartReason | None = Field(
        default=None,
        description="present only on the first answer of a chain that the service restarted: the stream id's "
        "previous chain was evicted (its key's quota or the store's cap), expired (idle past RAFD_STREAM_TTL_S), "
        "is too old for this frame (gap: more than RAFD_STREAM_GAP_RESTART_S seconds of timestamps before it) or "
        "is not the client's (previous_timestamp_mismatch: its last frame is not the request's previous_timestamp) "
        "or was detected over another view (view_changed: a scan of another size than the chain's); frames_used "
        "starts again at 1 and the odometry world frame restarts at this frame",
    )
    replayed: bool | None = Field(
        default=None,
        description="present (true) only when the frame repeats the stream's last accepted frame (same timestamp, "
        "image and pose, e.g. a retry after a lost answer): the answer is that frame's answer again, and the stream "
        "did not change",
    )
    pose_source: Literal["request", "odometry"]
    pose: Pose
    boxes: list[BoxOut]
    flow: FlowOut | None = Field(description="null with ?flow=false, on a stream's first frame or a 1-frame model")
    input: InputOut
    model: ModelRef
    timing: TimingOut

    def to_plain(self) -> dict[str, Any]:
        """The answer as sent, before JSON: fields by their names in the API ("class"), those never set left out
        (stream_restarted, replayed), the flow's arrays as built (numpy arrays for the list form: no warning that
        they are not lists)."""
        return self.model_dump(by_alias=True, exclude_unset=True, warnings=False)

    def to_json(self) -> bytes:
        # orjson writes a numpy array as the nested lists' very text, faster than .tolist() first
        # (tests/service/pipeline/test_detect.py), and a float32 validity as its shortest text (0.57).
        return orjson.dumps(self.to_plain(), option=orjson.OPT_SERIALIZE_NUMPY)


class StreamOut(Answer):
    stream_id: str
    generation: int = Field(
        description="increases each time the stream id starts a new chain (first frame, after a DELETE or an expiry)"
    )
    frames_buffered: int
    frames_seen: int
    frames_queued: int = Field(description="frames of this stream waiting or running now")
    last_timestamp: float | None
    idle_s: float = Field(description="seconds since the last ACCEPTED frame (refused frames do not count)")
    pose_source: str | None
    state_bytes: int


class StreamsResponse(Answer):
    count: int = Field(description="streams listed (with API keys: the caller's own)")
    max_streams: int
    max_streams_per_key: int = Field(description="the most streams one API key holds (its own LRU beyond)")
    ttl_s: float
    streams: list[StreamOut]


class PrecisionChoiceOut(Answer):
    cpu_precisions: list[str] = Field(description="the precisions this CPU can run the model in (fp32, bf16)")
    gate_records: dict[str, str] = Field(
        description="per reduced precision, the model's accuracy-gate record: pass, fail, none, or "
        "'pass on too little evidence' (`rafd gate MODEL` makes one)"
    )
    allowed_precisions: list[str] = Field(
        description="the precisions RAFD_PRECISION=auto may pick: fp32 and those this CPU runs whose gate passed"
    )
    reason: str = Field(description="why the service serves what it serves, in one sentence (also logged at start-up)")


class RuntimeOut(Answer):
    runtime: str
    precision: str
    threads: int = Field(description="threads of a model run alone")
    concurrent_runs: int
    threads_per_concurrent_run: int
    selection_ms_per_run: dict[str, float] = Field(
        description="RAFD_RUNTIME=auto: the median ms per run of every candidate timed at start-up"
    )
    precision_choice: PrecisionChoiceOut | None = Field(
        default=None, description="the precisions this CPU runs, which the model's gate records allow, and why"
    )
    float32_islands: list[str] = Field(
        default_factory=list,
        description="bf16 or int8 served with these units kept in float32 (the islands its gate passed with); "
        "empty for plain bf16, int8 with every matrix operation quantized, and fp32",
    )


class FullScanOut(Answer):
    side_px: int = Field(description="side of the square a full scan is detected over (RAFD_DETECT_RANGE_M)")
    tiles: int = Field(description="the model's inputs stepped over it, as one run")
    state_bytes: int = Field(
        description="the model's state a stream of full scans holds (its tracks add a few kB: GET /streams)"
    )
    model_ms: float | None = Field(
        description="median ms of the model stage of the last full scans served (timing.model_ms); null before one"
    )
    frames: int = Field(description="full scans that median is of (at most the last 64)")


class FarThresholdOut(Answer):
    from_m: float = Field(description="detections whose centre lies this far from the radar or farther use it")
    threshold: float = Field(description="they are answered when they score at or above it")


class ModelInfo(Answer):
    metadata: dict[str, str] = Field(description="the ONNX model's metadata (rafd.runtime.METADATA_KEYS and more)")
    config: dict[str, Any] = Field(description="the model's RaFDConfig")
    input_size: int
    num_frames: int
    feature_size: int
    cell_size_m: float
    resolution_m_per_px: float
    class_names: list[str]
    accepted_image_sizes: list[int]
    accepted_polar_shape: list[int] | None = Field(
        description="[range rows, azimuth columns] of a Navtech_Polar scan, accepted where a full RADIATE scan is"
    )
    accepted_native: dict[str, Any] | None = Field(
        description="native scans (Oxford Radar RobotCar, Boreas) are accepted where a full RADIATE scan is: the "
        "shape rule and each dataset's range bin in metres"
    )
    score_threshold: float = Field(description="detections scoring below it are not answered")
    far_score_threshold: FarThresholdOut | None = Field(
        description="the model's higher threshold for detections far from the radar (null: score_threshold at every "
        "range; RAFD_SCORE_THRESHOLD sets one threshold for every range)"
    )
    runtime: RuntimeOut = Field(description="how the graph runs")
    full_scan: FullScanOut | None = Field(
        description="what a full RADIATE scan (posted, or converted from a polar or native one) costs; null for a "
        "model that takes none"
    )


class Liveness(Answer):
    status: Literal["alive"]


class Readiness(Answer):
    status: Literal["ready"]
    model_version: str


class ErrorBody(BaseModel):
    code: str
    message: str


class ErrorResponse(BaseModel):
    error: ErrorBody
