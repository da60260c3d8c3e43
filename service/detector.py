"""The detect pipeline, in arrival order per stream, every stage bounded:

    receiving pool -> [ticket by arrival: X-Stream-Id / path form] -> body received (at the minimum rate,
    service/intake.py; a multipart PNG's chunk headers checked as it streams in) and parsed (JSON: parse executor)
    -> in-flight limit (only now: a slow body never holds a slot the model needs) -> [ticket by arrival: body form]
    -> placed (409 at once if out of order) -> PNG chunk check (event loop, headers only) -> decode executor ->
    hold for the same client's earlier frames still being parsed (service/ordering.py) -> wait for the stream's turn
    -> pose (odometry executor) -> runner step (model executor) -> commit -> boxes and flow.

A refused or failed frame changes no stream; a frame whose client left before its turn is dropped (499).
"""

from __future__ import annotations

import asyncio
import base64
import hashlib
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from fastapi import Request
from starlette.requests import ClientDisconnect

from rafd.detections import decode_detections
from rafd.flow_validity import FLOW_VALID_MIN, config_validity, search_reach_m
from rafd.geometry import box_polygons_pixels, relative_pose
from rafd.native import NativeShape
from rafd.protocol import operating_threshold, warming_up
from service import poses
from service.batcher import StepBatcher
from service.errors import ApiError, timestamp_error
from service.executors import AdmissionLimit, BoundedExecutor
from service.images import DecodedFrame, accepted_sizes, check_posted_image, decode_frame, upload_check
from service.intake import arrival_of, client_of
from service.metrics import ServiceMetrics
from service.ordering import ArrivalOrder, Unresolved
from service.requests import StructureCount, parse_detect_request, parse_json_body
from service.schemas import DetectBody, DetectFields, Pose
from service.settings import Settings
from service.streams import RestartReason, StreamEntry, StreamStore, Ticket

if TYPE_CHECKING:
    from rafd.runtime.streaming import Runner

FlowFormat = Literal["list", "base64"]
CELL_RULE = (
    "cell (i, j) = (row, col) covers posted pixels u in [origin_u + j*stride_px, +stride_px), "
    "v in [origin_v + i*stride_px, +stride_px); its centre in metres (ego frame): "
    "x = (j + 0.5 - width/2) * cell_size_m, y = (height/2 - i - 0.5) * cell_size_m"
)
FLOW_AXES = (
    "component 0 = x (right), component 1 = y (forward), metres in the newest frame's ego axes; ego motion removed"
)
# The answer's flow validity is rounded DOWN to 0.01 (a cell reaches validity_min in the answer only if it did), and
# written from these tables of k / 100: the list form's float32 (orjson writes each as its shortest text: 0.57, 1.0)
# and the base64 form's float16 (a lookup, 5 us for 64 x 64 where converting float32 to float16 takes 30), the
# float16 at or just above k / 100 (less than 0.0005 above): compared with any threshold of 2 decimals, as k / 100.
VALIDITY_STEPS = 100
_VALIDITY_EXACT = np.arange(VALIDITY_STEPS + 1) / VALIDITY_STEPS
_VALIDITY_FLOAT32 = _VALIDITY_EXACT.astype(np.float32)
_VALIDITY_FLOAT16 = _VALIDITY_EXACT.astype("<f2")
_VALIDITY_FLOAT16[_VALIDITY_FLOAT16 < _VALIDITY_EXACT] = np.nextafter(
    _VALIDITY_FLOAT16[_VALIDITY_FLOAT16 < _VALIDITY_EXACT], np.float16(np.inf)
)


@dataclass(frozen=True)
class DetectOptions:
    flow: bool = True
    flow_format: FlowFormat = "list"


@dataclass(frozen=True)
class Executors:
    """One bounded executor per stage, so a slow stage never queues the others' work (or health checks)."""

    parse: BoundedExecutor
    decode: BoundedExecutor
    odometry: BoundedExecutor
    model: BoundedExecutor

    @classmethod
    def from_settings(cls, settings: Settings, metrics: ServiceMetrics) -> Executors:
        def make(name: str, workers: int, queue_limit: int) -> BoundedExecutor:
            executor = BoundedExecutor(
                name, workers, queue_limit, settings.retry_after_s, on_refused=metrics.executor_refused
            )
            metrics.track_executor(name, lambda: executor.waiting)
            return executor

        return cls(
            parse=make("parse", settings.parse_workers, settings.parse_queue_limit),
            decode=make("decode", settings.decode_workers, settings.decode_queue_limit),
            odometry=make("odometry", settings.odometry_workers, settings.odometry_queue_limit),
            model=make("model", settings.concurrent_runs, settings.model_queue_limit),
        )

    def shutdown(self) -> None:
        for executor in (self.parse, self.decode, self.odometry, self.model):
            executor.shutdown()


class DetectService:
    """Everything /detect needs once the model is loaded: runner, stream store, executors, odometry, settings."""

    def __init__(
        self,
        runner: Runner,
        settings: Settings,
        store: StreamStore,
        metrics: ServiceMetrics,
        odometry: poses.Odometry | None = None,
        executors: Executors | None = None,
    ) -> None:
        self.runner = runner
        self.config = runner.config
        self.settings = settings
        self.store = store
        self.metrics = metrics
        self.executors = executors or Executors.from_settings(settings, metrics)
        self.receiving = AdmissionLimit(
            settings.max_receiving_requests, settings.retry_after_s, "receiving their body", "MAX_RECEIVING_REQUESTS"
        )
        self.admission = AdmissionLimit(settings.max_inflight_requests, settings.retry_after_s)
        self.order = ArrivalOrder(settings.order_hold_s)
        self._odometry = odometry
        self.batcher = StepBatcher(runner, self.executors.model, settings.max_batch, settings.batch_window_ms / 1000.0)
        self.batcher.on_batch = metrics.model_batch_size.observe
        # RAFD_SCORE_THRESHOLD when set, else the model's documented operating threshold (rafd.protocol)
        self.score_threshold = operating_threshold(runner.metadata, settings.score_threshold)
        # the native scan sizes accepted, checked from the PNG header before any inflating (rafd.native.NativeShape)
        self.native_shape = NativeShape(
            max_azimuths=settings.native_max_azimuths, max_range_bins=settings.native_max_range_bins
        )
        # metres the flow's matching reaches from a cell (the model's flow.stride and flow.local_radius, from the
        # config in its ONNX metadata): what a flow validity of 1 means (rafd.flow_validity)
        flow = self.config.flow
        self.flow_reach_m = search_reach_m(flow.stride, self.config.resolution, flow.local_radius)
        # Given every answer once it is complete, with the caller's key name (the live view's queue, service/live.py,
        # which publishes one key's streams only); must not block.
        self.on_answer: Callable[[dict[str, Any], DecodedFrame, str | None], None] | None = None

    @property
    def accepted_sizes(self) -> tuple[int, ...]:
        return accepted_sizes(self.config.input_size, self.config.resolution)

    async def detect(
        self, request: Request, stream_hint: str | None, caller: str | None, options: DetectOptions
    ) -> dict[str, Any]:
        """One frame of one stream -> the JSON answer; the stream changes only when everything succeeded.

        `stream_hint`: the stream id from the X-Stream-Id header or the path (None: from the body); with it the
        frame's place in the stream's queue is taken before the body is read. `caller`: the API key's name (the
        stream's namespace).
        """
        start = time.perf_counter()
        arrival, client = arrival_of(request.scope), client_of(request.scope)
        ticket: Ticket | None = None
        unresolved: Unresolved | None = None
        receiving = admitted = False
        self.receiving.enter()
        receiving = True
        try:
            if stream_hint is not None:
                ticket = self.store.take_ticket(stream_hint, caller, arrival)
            else:  # the same client's later frames hold their turn while this body arrives and is parsed
                unresolved = self.order.arrive(client, arrival)
            size, resolution = self.config.input_size, self.config.resolution
            native = self.native_shape
            fields, image = await self._read(request, stream_hint, lambda: upload_check(size, resolution, native))
            self.receiving.leave()
            receiving = False
            self.admission.enter()  # the in-flight limit: only once the body has arrived
            admitted = True
            if ticket is None:
                ticket = self.store.take_ticket(fields.stream_id, caller, arrival)
            if unresolved is not None:  # placed: frames that arrived after it now queue behind it
                self.order.resolve(unresolved)
                unresolved = None
            self.store.place(ticket, fields.timestamp)
            read_at = time.perf_counter()
            check_posted_image(image, size, resolution, native)  # chunk headers only: hostile files never take a slot
            decoded, digest = await self.executors.decode.run(
                _decode_and_digest, fields.pose, image, size, resolution, native
            )
            frame = decoded.model_input()  # [S, S] float32 in [0, 1]
            decoded_at = time.perf_counter()

            await self.order.wait_for_earlier(client, arrival)
            await self.store.wait_turn(ticket)
            if await request.is_disconnected():
                raise ClientDisconnect()  # nobody to answer: the frame is dropped before it changes the stream
            entry = self.store.check_turn(ticket)
            replay = _replay_or_refuse(entry, fields.timestamp, digest)
            if replay is not None:  # a retry of the last accepted frame: its answer again, the stream unchanged
                return {**replay, "replayed": True}
            chain_break = self.chain_break(entry, fields)
            poses.check_gap(entry.last_timestamp, fields.timestamp, self.settings.min_frame_gap_s)
            # A broken chain is not continued: this frame starts a new buffer, odometry world frame and pose source.
            state, last_odometry, last_pose, pose_source, last_timestamp = (
                (self.runner.new_state(), None, None, None, None)
                if chain_break
                else (entry.state, entry.odometry, entry.last_pose, entry.pose_source, entry.last_timestamp)
            )
            locked_at = time.perf_counter()
            if fields.pose is not None:
                poses.check_request_pose(pose_source)
                pose, source = np.array([fields.pose.x, fields.pose.y, fields.pose.yaw]), "request"
                memory = poses.remember(decoded.odometry_view, fields.timestamp, decoded.sweep)
            elif last_odometry is None:  # a chain's first frame anchors its odometry world frame
                pose, source = np.zeros(3), "odometry"
                memory = poses.remember(decoded.odometry_view, fields.timestamp, decoded.sweep)
            else:
                pose, memory = await self.executors.odometry.run(
                    poses.odometry_pose,
                    last_pose,
                    last_odometry,
                    decoded.odometry_view,
                    fields.timestamp,
                    decoded.sweep,
                    resolution,
                    self._odometry,
                )
                source = "odometry"
            # a pose faster than a road vehicle (a forged pose, a degenerate scan) would bend the chain for good
            poses.check_motion(last_pose, last_timestamp, pose, fields.timestamp, self.settings.max_speed_mps)
            odometry_done = time.perf_counter()
            # float64: world poses may be large (UTM metres); the runner takes differences before casting.
            result, new_state = await self.batcher.step(state, frame, pose)
            model_done = time.perf_counter()
            previous_timestamp, previous_pose = last_timestamp, last_pose
            self.store.commit(ticket, new_state, fields.timestamp, memory, pose, source, digest, chain_break)
        finally:
            if unresolved is not None:
                self.order.resolve(unresolved)
            if ticket is not None:
                self.store.release(ticket)
            if receiving:
                self.receiving.leave()
            if admitted:
                self.admission.leave()

        self.metrics.frames.inc()
        self.metrics.model_latency.observe(model_done - odometry_done)
        answer = self._answer(fields, decoded, result, pose, source, previous_timestamp, options, previous_pose)
        if ticket.restarted is not None:  # the first answer of a chain the service restarted says why
            answer["stream_restarted"] = ticket.restarted
        done = time.perf_counter()
        answer["timing"] = {
            "read_ms": _ms(read_at - start),
            "decode_ms": _ms(decoded_at - read_at),
            "wait_ms": _ms(locked_at - decoded_at),
            "odometry_ms": _ms(odometry_done - locked_at),
            "model_ms": _ms(model_done - odometry_done),
            "post_ms": _ms(done - model_done),
            "total_ms": _ms(done - start),
        }
        ticket.entry.remember_answer(fields.timestamp, digest, answer)  # for a retry whose answer was lost
        if self.on_answer is not None:
            self.on_answer(answer, decoded, caller)
        return answer

    def chain_break(self, entry: StreamEntry, fields: DetectFields) -> RestartReason | None:
        """Why the chain held here must not be continued by this frame, from the stream's own evidence; None to
        continue it. `gap`: more than RAFD_STREAM_GAP_RESTART_S seconds of timestamps since its last frame (frames
        missing here, e.g. sent to another replica meanwhile). `previous_timestamp_mismatch`: the client names
        another frame as its previous one than the chain's last (the frames in between went elsewhere)."""
        if not entry.frames_seen or entry.last_timestamp is None:
            return None  # a new chain: nothing to break
        limit = self.settings.stream_gap_restart_s
        if limit > 0 and fields.timestamp - entry.last_timestamp > limit:
            return "gap"
        if fields.previous_timestamp is not None and fields.previous_timestamp != entry.last_timestamp:
            return "previous_timestamp_mismatch"
        return None

    async def _read(self, request: Request, stream_hint: str | None, check: Any) -> tuple[DetectFields, Any]:
        """The parsed body, within RAFD_BODY_TIMEOUT_S: a slow body must not hold its stream's place forever."""
        parse = parse_detect_request(request, stream_hint, check, self._parse_json)
        try:
            if not hasattr(asyncio, "timeout"):  # Python 3.10
                return await asyncio.wait_for(parse, self.settings.body_timeout_s)
            # asyncio.timeout cancels this task at the deadline; wait_for runs the parse as another task, which
            # made refusing a hostile upload measurably slower (0.5 ms more server CPU each, here).
            async with asyncio.timeout(self.settings.body_timeout_s):
                return await parse
        except asyncio.TimeoutError as exc:
            raise ApiError(
                "body_timeout",
                f"the request body did not arrive within {self.settings.body_timeout_s} s (RAFD_BODY_TIMEOUT_S)",
            ) from exc

    async def _parse_json(self, raw: bytes, counted: StructureCount) -> tuple[DetectBody, str]:
        """A JSON body (its structure counted as it arrived) parsed and validated on the parse executor."""
        return await self.executors.parse.run(parse_json_body, raw, counted)

    # ------------------------------------------------------------------ post-processing
    def _answer(
        self,
        fields: DetectFields,
        decoded: DecodedFrame,
        result: Any,
        pose: np.ndarray,
        source: str,
        previous_timestamp: float | None,
        options: DetectOptions,
        previous_pose: np.ndarray | None = None,
    ) -> dict[str, Any]:
        cfg = self.config
        frames_used = int(result.frames_used)
        metadata = self.runner.metadata
        return {
            "stream_id": fields.stream_id,
            "timestamp": fields.timestamp,
            "frames_used": frames_used,
            "num_frames": cfg.num_frames,
            "warming_up": warming_up(frames_used, cfg.num_frames),
            "pose_source": source,
            "pose": {"x": float(pose[0]), "y": float(pose[1]), "yaw": float(pose[2])},
            "boxes": self._boxes(result, decoded.posted_size),
            "flow": self._flow(result, decoded, previous_timestamp, fields.timestamp, options, previous_pose, pose),
            "input": {
                "posted_size": decoded.posted_size,
                "model_size": cfg.input_size,
                "crop_offset_px": decoded.crop_offset,
                "posted_format": decoded.posted_format,
            },
            "model": {
                "version": metadata.get("version", "unknown"),
                "checkpoint_sha256": metadata.get("checkpoint_sha256", "unknown"),
                "runtime": self.runner.runtime,
                "precision": self.runner.precision,
            },
        }

    def _boxes(self, result: Any, posted_size: int) -> list[dict[str, Any]]:
        detections = decode_detections(result.boxes, result.scores, self.score_threshold)
        polygons = box_polygons_pixels(detections.boxes, posted_size, self.config.resolution)  # [N, 4, 2]
        names = self.config.class_names
        out = []
        for box, score, label, polygon in zip(detections.boxes, detections.scores, detections.labels, polygons):
            out.append(
                {
                    # 0.1 mm and 1e-5 rad: far below the radar's 17 cm pixels, keeps the JSON short
                    "x": round(float(box[0]), 4),
                    "y": round(float(box[1]), 4),
                    "width": round(float(box[2]), 4),
                    "length": round(float(box[3]), 4),
                    "yaw": round(float(box[4]), 5),
                    "score": round(float(score), 5),
                    "class_id": int(label),
                    "class": names[label] if label < len(names) else str(label),
                    "polygon": np.round(polygon, 2).tolist(),
                }
            )
        return out

    def _flow(
        self,
        result: Any,
        decoded: DecodedFrame,
        previous_timestamp: float | None,
        timestamp: float,
        options: DetectOptions,
        previous_pose: np.ndarray | None = None,
        pose: np.ndarray | None = None,
    ) -> dict[str, Any] | None:
        """The newest pair's flow [2, Hf, Wf] and its validity [Hf, Wf]; None when not asked for or no real pair
        exists yet."""
        if not options.flow or result.flow is None or result.frames_used < 2:
            return None
        flow = np.asarray(result.flow)[-1]  # [T-1, 2, Hf, Wf] -> [2, Hf, Wf] newest pair
        _, height, width = flow.shape
        stride = self.config.input_size // height
        cell = self.config.cell_size
        steps = self.validity_steps(previous_pose, pose, result.frames_used, height)  # [Hf, Wf] of k / 100
        if options.flow_format == "base64":
            values: Any = base64.b64encode(flow.astype("<f2").tobytes()).decode("ascii")
            validity: Any = base64.b64encode(_VALIDITY_FLOAT16.take(steps).tobytes()).decode("ascii")
            encoding = "base64-float16"
        else:
            # millimetres: well below a cell. Left an array: the route's orjson writes it as nested lists
            # (OPT_SERIALIZE_NUMPY), the same text as .tolist() first, in 0.16 ms instead of 0.27 for 2 x 64 x 64.
            values = np.round(flow.astype(np.float64), 3)
            validity = _VALIDITY_FLOAT32.take(steps)
            encoding = "list"
        return {
            "pair": [previous_timestamp, timestamp],
            "shape": [2, height, width],
            "units": "m",
            "axes": FLOW_AXES,
            "grid": {
                "height": height,
                "width": width,
                "cell_size_m": cell,
                "stride_px": stride,
                "origin_px": [decoded.crop_offset, decoded.crop_offset],
                "cell_centre_rule": CELL_RULE,
            },
            "encoding": encoding,
            "values": values,
            "validity": validity,
            "validity_min": FLOW_VALID_MIN,
            "search_reach_m": round(self.flow_reach_m, 4),
        }

    def validity_steps(
        self, previous_pose: np.ndarray | None, pose: np.ndarray | None, frames_used: int, feature_size: int
    ) -> np.ndarray:
        """[Hf, Wf] integers k in [0, VALIDITY_STEPS]: the newest pair's flow validity (rafd.flow_validity, from the
        pair's relative pose as the model aligned it: the request's poses or odometry's) is k / VALIDITY_STEPS,
        rounded down. All 0 when the window holds no real pair (a stream's first frame: its window is copies of it,
        nothing was measured)."""
        if frames_used < 2 or previous_pose is None or pose is None:
            return np.zeros((feature_size, feature_size), np.intp)
        validity = config_validity(self.config, relative_pose(previous_pose, pose))  # [Hf, Wf]
        # Down (the cast truncates: the floor of these non-negative numbers), in float64 where a float32 times 100
        # is exact: a cell below validity_min stays below it.
        steps: np.ndarray = np.multiply(validity, float(VALIDITY_STEPS), dtype=np.float64)
        return steps.astype(np.intp)


def frame_digest(pose: Pose | None, image: bytes | str) -> bytes:
    """What makes a frame the same frame again (a retry): its image as posted and its pose (sha256, 0.5 ms per
    0.9 MB here; run on the decode executor)."""
    digest = hashlib.sha256(image.encode("ascii", "replace") if isinstance(image, str) else image)
    if pose is not None:
        digest.update(repr((pose.x, pose.y, pose.yaw)).encode())
    return digest.digest()


def _decode_and_digest(pose: Pose | None, image: bytes | str, *decode_args: Any) -> tuple[DecodedFrame, bytes]:
    """One decode-executor job: the decoded frame and its digest."""
    return decode_frame(image, *decode_args), frame_digest(pose, image)


def _replay_or_refuse(entry: StreamEntry, timestamp: float, digest: bytes) -> dict[str, Any] | None:
    """At the frame's turn: the last accepted frame's answer when this is that frame again; 409 when it has the last
    frame's timestamp but another image or pose; None for a new frame."""
    if entry.last_timestamp is None or timestamp != entry.last_timestamp:
        return None
    replay = entry.replay_of(timestamp, digest)
    if replay is None:
        raise timestamp_error(
            entry.stream_id,
            f"timestamp {timestamp!r} is the stream's last accepted frame's, with another image or pose (only the "
            "same frame posted again is answered again)",
        )
    return replay


def _ms(seconds: float) -> float:
    return round(seconds * 1000.0, 3)
