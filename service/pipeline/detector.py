"""The detect pipeline, in arrival order per stream, every stage bounded:

    receiving pool -> [ticket by arrival: X-Stream-Id / path form] -> body received (at the minimum rate,
    service/http/intake.py; a multipart PNG's chunk headers checked as it streams in) and parsed (JSON: parse executor)
    -> in-flight limit (only now: a slow body never holds a slot the model needs) -> [ticket by arrival: body form]
    -> placed (409 at once if out of order) -> PNG chunk check (event loop, headers only) -> decode executor ->
    hold for the same client's earlier frames still being parsed (service/pipeline/ordering.py) -> wait for the stream's
    turn -> pose (odometry executor) -> runner step (model executor) -> commit -> boxes and flow.

`DetectService.detect` runs these stages in this order, one method each. What a request holds on the way (its
receiving and in-flight slots, its place among its client's requests and in its stream's queue) is a context manager
on one exit stack, left however the request ends; a `StageClock` records the answer's timing.

A refused or failed frame changes no stream; a frame whose client left before its turn is dropped (499).
"""

from __future__ import annotations

import asyncio
import base64
import dataclasses
import hashlib
import time
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import AsyncExitStack, contextmanager
from dataclasses import dataclass
from functools import partial
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from fastapi import Request
from pydantic import TypeAdapter
from starlette.requests import ClientDisconnect

from rafd import flow_png, tracking
from rafd.flow_validity import FLOW_VALID_MIN, config_validity, search_reach_m
from rafd.geometry import box_polygons_pixels, relative_pose
from rafd.protocol import operating_threshold, warming_up
from rafd.runtime.view import View, step_view
from rafd.scans.cartesian import accepted_sizes
from rafd.scans.native import NativeShape
from service.body.images import (
    DecodedFrame,
    PostedImage,
    check_posted_image,
    decode_frame,
    upload_check,
)
from service.body.requests import StructureCount, parse_detect_request, parse_json_body
from service.http.errors import ApiError, client_of, timestamp_error
from service.http.intake import arrival_of
from service.loading import full_scan_view
from service.pipeline import poses
from service.pipeline.executors import AdmissionLimit, BoundedExecutor
from service.pipeline.ordering import ArrivalOrder, Unresolved
from service.pipeline.service_metrics import ServiceMetrics
from service.pipeline.streams import ArrivalKey, Chain, StreamEntry, StreamStore, Ticket
from service.schemas import (
    BoxOut,
    CoveredOut,
    DetectBody,
    DetectFields,
    DetectResponse,
    FlowGrid,
    FlowOut,
    InputOut,
    ModelRef,
    Pose,
    RestartReason,
    TimingOut,
)
from service.settings import Settings

if TYPE_CHECKING:
    from rafd.runtime.streaming import Runner, StepResult, StreamState

FlowFormat = Literal["list", "base64", "png"]
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


_BOXES = TypeAdapter(list[BoxOut])


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


@dataclass(frozen=True)
class Arrival:
    """Who sent a frame and when its request arrived: what orders it among its stream's frames and its client's."""

    caller: str | None  # the API key's name: the stream's namespace
    key: ArrivalKey
    client: str  # the client's address

    @classmethod
    def of(cls, request: Request, caller: str | None) -> Arrival:
        return cls(caller, arrival_of(request.scope), client_of(request.scope))


@dataclass(frozen=True)
class Seen:
    """What the model and the tracker made of one frame."""

    result: StepResult  # each tile's outputs
    tracked: tracking.TrackedBoxes  # the answered boxes with their tracks, ego frame
    state: StreamState  # the model's state after the frame
    tracks: tracking.TrackerState  # the tracks after the frame


@dataclass(frozen=True)
class FramePose:
    """A frame's world pose, where it came from, and what its stream keeps of it for the next frame's odometry."""

    pose: np.ndarray  # [3] float64: world poses may be large (UTM metres); the runner takes differences first
    source: Literal["request", "odometry"]
    memory: poses.OdometryMemory


class StageClock:
    """How long each stage of one request took, a stage ending at its `lap`: the answer's timing, kept out of the
    stages themselves."""

    def __init__(self) -> None:
        self.start = self._last = time.perf_counter()
        self.seconds: dict[str, float] = {}

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        self.seconds[stage] = now - self._last
        self._last = now

    def timing(self) -> TimingOut:
        """Every stage so far, `post` (since the last lap) and the total, in milliseconds; validated, so a stage not
        in the answer's schema fails loudly."""
        self.lap("post")
        stages = {f"{stage}_ms": _ms(seconds) for stage, seconds in self.seconds.items()}
        return TimingOut.model_validate({**stages, "total_ms": _ms(self._last - self.start)})


@contextmanager
def _holding(limit: AdmissionLimit) -> Iterator[None]:
    """A slot of `limit` for the block (503 `overloaded` when none is free)."""
    limit.enter()
    try:
        yield
    finally:
        limit.leave()


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
        # RAFD_SCORE_THRESHOLD when set, else the model's documented operating threshold (rafd.protocol)
        self.score_threshold = operating_threshold(runner.metadata, settings.score_threshold)
        # the native scan sizes accepted, checked from the PNG header before any inflating
        # (rafd.scans.native.NativeShape)
        self.native_shape = NativeShape(
            max_azimuths=settings.native_max_azimuths, max_range_bins=settings.native_max_range_bins
        )
        # metres the flow's matching reaches from a cell (the model's flow.stride and flow.local_radius, from the
        # config in its ONNX metadata): what a flow validity of 1 means (rafd.flow_validity)
        flow = self.config.flow
        self.flow_reach_m = search_reach_m(flow.stride, self.config.resolution, flow.local_radius)
        self._views: dict[int, View] = {}  # posted scan side -> what it is detected over (view_for)
        self.tracker_settings = dataclasses.replace(
            tracking.DEFAULT_SETTINGS,
            answer_tentative=settings.tracks_answer_tentative,
            answer_coasting=settings.tracks_answer_coasting,
        )
        # what a full scan is detected over (None: the model takes none), and its model stage's last seconds
        self.full_scan = full_scan_view(self.config, settings.detect_range_m)
        self._full_scan_seconds: deque[float] = deque(maxlen=64)
        # Given every answer once it is complete, with the caller's key name (the live view's queue,
        # service/pipeline/live.py, which publishes one key's streams only); must not block.
        self.on_answer: Callable[[dict[str, Any], DecodedFrame, str | None], None] | None = None

    @property
    def accepted_sizes(self) -> tuple[int, ...]:
        return accepted_sizes(self.config.input_size, self.config.resolution)

    def covered_side(self, posted_size: int) -> int:
        """The side of the square a Cartesian scan of this side is detected over (view_for)."""
        return self.view_for(posted_size).side_px

    def view_for(self, posted_size: int) -> View:
        """What a Cartesian scan of this side is detected over (rafd.runtime.view: the whole scan, or within
        RAFD_DETECT_RANGE_M of the radar; a scan of the model's size is one tile)."""
        view = self._views.get(posted_size)
        if view is None:
            cfg = self.config
            cell_px = cfg.input_size // cfg.feature_size
            view = View.of(posted_size, cfg.input_size, cfg.resolution, cell_px, self.settings.detect_range_m)
            self._views[posted_size] = view
        return view

    def full_scan_cost(self) -> dict[str, float | int | None] | None:
        """What a full scan costs: its tiles, the state a stream of them holds and the median model stage of the
        last full scans served (None before the first)."""
        if self.full_scan is None:
            return None
        seconds = sorted(self._full_scan_seconds)
        return {
            "side_px": self.full_scan.side_px,
            "tiles": len(self.full_scan.tiles),
            "state_bytes": self.runner.state_bytes(len(self.full_scan.tiles)),
            "model_ms": round(1e3 * seconds[len(seconds) // 2], 1) if seconds else None,
            "frames": len(seconds),
        }

    @property
    def image_rule(self) -> tuple[int, float, NativeShape]:
        """What a posted image is checked and decoded against: the model's input size and resolution, and the native
        scan shapes accepted."""
        return self.config.input_size, self.config.resolution, self.native_shape

    async def detect(
        self, request: Request, stream_hint: str | None, caller: str | None, options: DetectOptions
    ) -> DetectResponse:
        """One frame of one stream -> its answer; the stream changes only when everything succeeded.

        `stream_hint`: the stream id from the X-Stream-Id header or the path (None: from the body); with it the
        frame's place in the stream's queue is taken before the body is read. `caller`: the API key's name (the
        stream's namespace).
        """
        clock, arrival = StageClock(), Arrival.of(request, caller)
        async with AsyncExitStack() as held:  # the frame's slots and places, left however the request ends
            fields, image, ticket = await self._received(held, request, stream_hint, arrival)
            clock.lap("read")
            decoded, digest = await self._decoded(fields, image)
            view = self.view_for(decoded.posted_size)
            clock.lap("decode")
            entry = await self._turn(request, ticket, arrival)
            replay = _replay_or_refuse(entry, fields.timestamp, digest)
            if replay is not None:  # a retry of the last accepted frame: its answer again, the stream unchanged
                return replay.model_copy(update={"replayed": True})
            chain, broken = self._chain(entry, fields, view)
            clock.lap("wait")
            located = await self._locate(fields, decoded, chain)
            clock.lap("odometry")
            seen = await self.executors.model.run(
                self._seen, chain, view, decoded.covered, located.pose, fields.timestamp
            )
            clock.lap("model")
            if view == self.full_scan:
                self._full_scan_seconds.append(clock.seconds["model"])
            advanced = chain.advanced(
                seen.state, located.memory, located.pose, located.source, fields.timestamp, view, seen.tracks
            )
            self.store.commit(ticket, advanced, digest, broken)
        self.metrics.frames.inc()
        self.metrics.model_latency.observe(clock.seconds["model"])
        answer = self._answer(fields, decoded, view, seen, located, chain, options, ticket.restarted, clock)
        ticket.entry.remember_answer(fields.timestamp, digest, answer)  # for a retry whose answer was lost
        if self.on_answer is not None:
            self.on_answer(answer.to_plain(), decoded, caller)
        return answer

    # ------------------------------------------------------------------ stages
    async def _received(
        self, held: AsyncExitStack, request: Request, stream_hint: str | None, arrival: Arrival
    ) -> tuple[DetectFields, PostedImage, Ticket]:
        """The body received and parsed (in a receiving slot), then the frame in flight (an in-flight slot: only once
        its body has arrived, so a slow body never holds a slot the model needs) and placed in its stream's queue;
        409 at once if it can no longer be in order."""
        with _holding(self.receiving):
            early = self._queue_early(held, stream_hint, arrival)
            fields, image = await self._read(request, stream_hint)
        held.enter_context(_holding(self.admission))
        ticket = early if isinstance(early, Ticket) else self._queue_parsed(held, early, fields.stream_id, arrival)
        self.store.place(ticket, fields.timestamp)
        return fields, image, ticket

    def _queue_early(self, held: AsyncExitStack, stream_hint: str | None, arrival: Arrival) -> Ticket | Unresolved:
        """Before the body: the frame's place in its stream's queue when the stream is named outside the body, else
        among its client's requests whose stream is not known yet (the same client's later frames hold their turn
        while this body arrives and is parsed)."""
        if stream_hint is not None:
            return held.enter_context(self.store.queued(stream_hint, arrival.caller, arrival.key))
        return held.enter_context(self._unresolved(arrival))

    def _queue_parsed(self, held: AsyncExitStack, unresolved: Unresolved, stream_id: str, arrival: Arrival) -> Ticket:
        """The frame's place in the stream its body named, by its arrival; its client's frames that arrived after
        it now queue behind it instead of waiting for it."""
        ticket = held.enter_context(self.store.queued(stream_id, arrival.caller, arrival.key))
        self.order.resolve(unresolved)
        return ticket

    @contextmanager
    def _unresolved(self, arrival: Arrival) -> Iterator[Unresolved]:
        """A request of the client whose stream is not known yet, until resolved or the request ends."""
        unresolved = self.order.arrive(arrival.client, arrival.key)
        try:
            yield unresolved
        finally:
            self.order.resolve(unresolved)

    async def _read(self, request: Request, stream_hint: str | None) -> tuple[DetectFields, PostedImage]:
        """The parsed body, within RAFD_BODY_TIMEOUT_S: a slow body must not hold its stream's place forever."""
        parse = parse_detect_request(request, stream_hint, partial(upload_check, *self.image_rule), self._parse_json)
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

    async def _decoded(self, fields: DetectFields, image: PostedImage) -> tuple[DecodedFrame, bytes]:
        """The image decoded (decode executor) into the square it is detected over and odometry's view, and the
        frame's digest (what makes a retry the same frame)."""
        check_posted_image(image, *self.image_rule)  # chunk headers only: hostile files never take a decode worker
        return await self.executors.decode.run(
            _decode_and_digest,
            fields.pose,
            fields.range_resolution_m,
            self.covered_side,
            image,
            *self.image_rule,
        )

    def _seen(self, chain: Chain, view: View, covered: np.ndarray, pose: np.ndarray, timestamp: float) -> Seen:
        """The model's step over the view's tiles, their merged detections and those detections' tracks (one job of
        the model executor)."""
        result, state = step_view(self.runner, chain.model, view, covered, pose)
        detections = view.merge(result.boxes, result.scores, self.score_threshold)
        tracked, tracks = tracking.step(
            chain.tracks,
            detections.boxes,
            pose,
            timestamp,
            scores=detections.scores,
            labels=detections.labels,
            settings=self.tracker_settings,
        )
        return Seen(result, tracked, state, tracks)

    async def _turn(self, request: Request, ticket: Ticket, arrival: Arrival) -> StreamEntry:
        """Once the same client's earlier frames still being parsed are placed (RAFD_ORDER_HOLD_S at most) and the
        stream's earlier frames are done: the stream's entry, still this chain's."""
        await self.order.wait_for_unresolved(arrival.client)
        await self.store.wait_turn(ticket)
        if await request.is_disconnected():
            raise ClientDisconnect()  # nobody to answer: the frame is dropped before it changes the stream
        return self.store.check_turn(ticket)  # the chain may have ended while the disconnect was checked

    def _chain(self, entry: StreamEntry, fields: DetectFields, view: View) -> tuple[Chain, RestartReason | None]:
        """The chain the frame continues: the stream's, or a new one when the stream's is not to be continued
        (`chain_break`: why); 422 when the frame follows the stream's last one too closely."""
        broken = self.chain_break(entry, fields, view)
        poses.check_gap(entry.last_timestamp, fields.timestamp, self.settings.min_frame_gap_s)
        if broken is not None:  # a new model state, odometry world frame and pose source, from this frame
            return Chain(), broken
        return entry.chain, None

    def chain_break(self, entry: StreamEntry, fields: DetectFields, view: View) -> RestartReason | None:
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
        if entry.chain.view is not None and entry.chain.view.tiling != view.tiling:
            return "view_changed"
        return None

    async def _locate(self, fields: DetectFields, decoded: DecodedFrame, chain: Chain) -> FramePose:
        """The frame's world pose; 422 when it is further from the chain's last pose than a road vehicle goes (a
        forged pose, a degenerate scan), which would bend the chain for good."""
        located = await self._pose(fields, decoded, chain)
        poses.check_motion(chain.pose, chain.timestamp, located.pose, fields.timestamp, self.settings.max_speed_mps)
        return located

    async def _pose(self, fields: DetectFields, decoded: DecodedFrame, chain: Chain) -> FramePose:
        """The request's pose; without one, the origin on a chain's first frame (it anchors the chain's odometry world
        frame), else odometry's from the chain's last frame (odometry executor)."""
        if fields.pose is None and chain.odometry is not None and chain.pose is not None:
            pose, memory = await self.executors.odometry.run(
                poses.odometry_pose,
                chain.pose,
                chain.odometry,
                decoded.odometry_view,
                fields.timestamp,
                decoded.sweep,
                self.config.resolution,
                self._odometry,
            )
            return FramePose(pose, "odometry", memory)
        memory = poses.remember(decoded.odometry_view, fields.timestamp, decoded.sweep)
        if fields.pose is None:
            return FramePose(np.zeros(3), "odometry", memory)
        poses.check_request_pose(chain.pose_source)
        return FramePose(np.array([fields.pose.x, fields.pose.y, fields.pose.yaw]), "request", memory)

    # ------------------------------------------------------------------ the answer
    def _answer(
        self,
        fields: DetectFields,
        decoded: DecodedFrame,
        view: View,
        seen: Seen,
        located: FramePose,
        chain: Chain,
        options: DetectOptions,
        restarted: RestartReason | None,
        clock: StageClock,
    ) -> DetectResponse:
        """The answer, built unvalidated (`model_construct`): its parts are the service's own, and the flow's list
        form stays a numpy array that orjson writes (DetectResponse.to_json). Fields left unset are not sent."""
        frames_used, num_frames = int(seen.result.frames_used), self.config.num_frames
        pose = located.pose
        # stream_restarted: only on the first answer of a chain the service restarted, saying why
        restart: dict[str, Any] = {} if restarted is None else {"stream_restarted": restarted}
        return DetectResponse.model_construct(
            stream_id=fields.stream_id,
            timestamp=fields.timestamp,
            frames_used=frames_used,
            num_frames=num_frames,
            warming_up=warming_up(frames_used, num_frames),
            pose_source=located.source,
            pose=Pose.model_construct(x=float(pose[0]), y=float(pose[1]), yaw=float(pose[2])),
            boxes=self._boxes(view, seen.tracked, chain.token),
            flow=self._flow(view, seen.result, chain, located, fields.timestamp, options),
            input=InputOut.model_construct(
                posted_size=decoded.posted_size,
                model_size=self.config.input_size,
                posted_format=decoded.posted_format,
                covered=covered_out(view),
                **native_input(decoded),
            ),
            model=self._model_ref(),
            **restart,
            timing=clock.timing(),  # last: the post stage ends once the rest is built
        )

    def _model_ref(self) -> ModelRef:
        metadata = self.runner.metadata
        return ModelRef.model_construct(
            version=metadata.get("version", "unknown"),
            checkpoint_sha256=metadata.get("checkpoint_sha256", "unknown"),
            runtime=self.runner.runtime,
            precision=self.runner.precision,
        )

    def _boxes(self, view: View, tracked: tracking.TrackedBoxes, token: str) -> list[BoxOut]:
        """The answered boxes with their tracks; the velocity and its covariance rounded to mm/s and (mm/s)^2."""
        polygons = box_polygons_pixels(tracked.boxes, view.posted_size, self.config.resolution)  # [N, 4, 2]
        names = self.config.class_names
        measured = tracked.velocity_source != tracking.VELOCITY_SOURCES.index("none")
        velocities = np.round(tracked.velocity, 3).tolist()
        covariances = np.round(tracked.velocity_covariance, 6).tolist()
        # Validated, unlike the rest of the answer: validating these few numbers at once is faster than
        # model_construct on each box.
        return _BOXES.validate_python(
            [
                {
                    # 0.1 mm and 1e-5 rad: far below the radar's 17 cm pixels, keeps the JSON short
                    "x": round(float(box[0]), 4),
                    "y": round(float(box[1]), 4),
                    "width": round(float(box[2]), 4),
                    "length": round(float(box[3]), 4),
                    "yaw": round(float(box[4]), 5),
                    "score": round(float(tracked.scores[k]), 5),
                    "class_id": int(tracked.labels[k]),
                    "class": names[tracked.labels[k]] if tracked.labels[k] < len(names) else str(tracked.labels[k]),
                    "polygon": polygon,
                    "track_id": f"{token}-{int(tracked.track_id[k])}",
                    "track": {
                        "status": tracking.STATUS_NAMES[int(tracked.status[k])],
                        "age": int(tracked.age[k]),
                        "hits": int(tracked.hits[k]),
                    },
                    "velocity": {"x": velocities[k][0], "y": velocities[k][1]} if measured[k] else None,
                    "velocity_covariance": covariances[k] if measured[k] else None,
                    "velocity_source": tracking.VELOCITY_SOURCES[int(tracked.velocity_source[k])],
                }
                # the polygons rounded at once: the same numbers as box by box, in a sixth of the time
                for k, (box, polygon) in enumerate(zip(tracked.boxes, np.round(polygons, 2).tolist()))
            ]
        )

    def _flow(
        self, view: View, result: StepResult, chain: Chain, located: FramePose, timestamp: float, options: DetectOptions
    ) -> FlowOut | None:
        """The newest pair's flow [2, H, W] over the view and its validity [H, W] (each cell from the tile whose core
        holds it, rafd.runtime.view); None when not asked for or no real pair exists yet."""
        if not options.flow or result.flow is None or result.frames_used < 2 or chain.pose is None:
            return None
        flow = view.mosaic(np.asarray(result.flow))  # [2, H, W] the newest pair
        _, height, width = flow.shape
        steps = view.mosaic(self.validity_steps(view, chain.pose, located.pose))  # [H, W] of k / 100
        if options.flow_format == "base64":
            values: Any = base64.b64encode(flow.astype("<f2").tobytes()).decode("ascii")
            validity: Any = base64.b64encode(_VALIDITY_FLOAT16.take(steps).tobytes()).decode("ascii")
            encoding = "base64-float16"
        elif options.flow_format == "png":  # rafd.flow_png: lossless to 1 mm, a fraction of the others' size
            values = base64.b64encode(flow_png.encode_flow(flow)).decode("ascii")
            validity = base64.b64encode(flow_png.encode_steps(steps)).decode("ascii")
            encoding = "png"
        else:
            # millimetres: well below a cell. Left an array: the route's orjson writes it as nested lists
            # (OPT_SERIALIZE_NUMPY), the same text as .tolist() first, in 0.16 ms instead of 0.27 for 2 x 64 x 64.
            values = np.round(flow.astype(np.float64), 3)
            validity = _VALIDITY_FLOAT32.take(steps)
            encoding = "list"
        grid = FlowGrid.model_construct(
            height=height,
            width=width,
            cell_size_m=self.config.cell_size,
            stride_px=view.cell_px,
            origin_px=[view.origin_px, view.origin_px],
            cell_centre_rule=CELL_RULE,
        )
        return FlowOut.model_construct(
            pair=[chain.timestamp, timestamp],
            shape=[2, height, width],
            units="m",
            axes=FLOW_AXES,
            grid=grid,
            encoding=encoding,
            values=values,
            validity=validity,
            validity_min=FLOW_VALID_MIN,
            search_reach_m=round(self.flow_reach_m, 4),
        )

    def validity_steps(self, view: View, previous_pose: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """[V, Hf, Wf] integers k in [0, VALIDITY_STEPS]: each tile's newest pair flow validity (rafd.flow_validity,
        from the tile's relative pose as the model aligned it: the request's poses or odometry's, moved to the tile's
        frame) is k / VALIDITY_STEPS, rounded down."""
        relative = relative_pose(view.tile_poses(previous_pose), view.tile_poses(pose))  # [V, 3]
        validity = np.stack([config_validity(self.config, motion) for motion in relative])  # [V, Hf, Wf]
        # Down (the cast truncates: the floor of these non-negative numbers), in float64 where a float32 times 100
        # is exact: a cell below validity_min stays below it.
        steps: np.ndarray = np.multiply(validity, float(VALIDITY_STEPS), dtype=np.float64)
        return steps.astype(np.intp)


def covered_out(view: View) -> CoveredOut:
    """What the answer says the view covered."""
    return CoveredOut.model_construct(
        side_px=view.side_px,
        offset_px=view.origin_px,
        side_m=round(view.side_px * view.grid.resolution, 3),
        range_m=None if view.range_m is None else round(view.range_m, 3),
        tiles=len(view.tiles),
    )


def native_input(decoded: DecodedFrame) -> dict[str, Any]:
    """The answer's input fields of a native scan (its format and range bin); none for other scans (left out)."""
    if decoded.native_format is None:
        return {}
    return {"native_format": decoded.native_format, "native_range_bin_m": decoded.native_range_bin_m}


def frame_digest(pose: Pose | None, image: bytes | str, range_bin_m: float | None = None) -> bytes:
    """What makes a frame the same frame again (a retry): its image as posted, its pose and its range bin (sha256,
    0.5 ms per 0.9 MB here; run on the decode executor)."""
    digest = hashlib.sha256(image.encode("ascii", "replace") if isinstance(image, str) else image)
    if pose is not None:
        digest.update(repr((pose.x, pose.y, pose.yaw)).encode())
    if range_bin_m is not None:
        digest.update(repr(("range_resolution_m", range_bin_m)).encode())
    return digest.digest()


def _decode_and_digest(
    pose: Pose | None,
    range_bin_m: float | None,
    covered: Callable[[int], int],
    image: bytes | str,
    input_size: int,
    resolution: float,
    native: NativeShape,
) -> tuple[DecodedFrame, bytes]:
    """One decode-executor job: the decoded frame and its digest."""
    decoded = decode_frame(image, input_size, resolution, native, range_bin_m, covered)
    return decoded, frame_digest(pose, image, range_bin_m)


def _replay_or_refuse(entry: StreamEntry, timestamp: float, digest: bytes) -> DetectResponse | None:
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
