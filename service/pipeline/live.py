"""The live view: every answered frame published to a Foxglove WebSocket server (`rafd serve --foxglove-port N`,
RAFD_FOXGLOVE_PORT; off by default), in the channels and schemas of the MCAP logs (rafd.viz.mcap.RadarChannels:
scan, scan grid, pose, boxes on the scan and in 3D, flow, velocities), one topic prefix per stream:
`/<stream_id>/radar/...` and `/<stream_id>/tf`. Open Foxglove, connect to ws://HOST:N and pick a stream's topics.

Off the request path, and out of the service's process: /detect only offers the answer to a bounded queue
(`put_nowait`, microseconds) and returns; a publisher process (spawned at start-up, niced) builds the messages
(Python objects: done in the service's process they would hold its interpreter lock from the requests) and runs
foxglove-sdk's server. A full queue drops the frame (counted in rafd_live_view_dropped_total): a slow viewer or a
busy CPU never slows /detect. The scan published is the square the answer covered (input.covered: the whole posted
scan by default), the boxes drawn on it in its pixels, velocity arrows per tracked box; flow arrows only where the
flow was measured (the answer's flow `validity` at or above its `validity_min`) and means something (cells with
returns or near a box, rafd.viz.flow_cells.meaningful_cells).

Who sees what: foxglove-sdk's WebSocket server has no authentication of its own, so whoever reaches its port sees
every stream published there (ids, scans, poses, boxes). Without API keys that is every stream (one namespace, as
for the HTTP API). With API keys only the streams of ONE key are published, the key named by RAFD_FOXGLOVE_KEY
(required then: the service does not start without it): other keys' answers never leave the service's process, so
two keys' streams that share an id are never merged on one topic, and no other key's stream id is advertised.

foxglove-sdk is the `live` extra (not in `serve`: the serving image stays without it unless built with
EXTRAS=serve,live); without it --foxglove-port stops the service at start-up saying which extra to install.
"""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import multiprocessing
import os
import queue
from collections import OrderedDict
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, Any

from prometheus_client import Counter, Gauge

from service.settings import Settings

if TYPE_CHECKING:
    from service.body.images import DecodedFrame
    from service.pipeline.service_metrics import ServiceMetrics

log = logging.getLogger(__name__)

MISSING_EXTRA = (
    "--foxglove-port (RAFD_FOXGLOVE_PORT) needs foxglove-sdk, which this installation lacks: "
    "pip install 'rafd[live]' (the serving image: docker build --build-arg EXTRAS=serve,live .)"
)
MAX_STREAM_CHANNELS = 64  # streams with open channels; the least recently published beyond it are closed
START_TIMEOUT_S = 60.0
PUBLISHER_NICENESS = 10  # the publisher yields the CPU to the service's requests


def check_available() -> None:
    """ValueError with the extra to install when foxglove-sdk is not installed (found without importing it)."""
    try:
        found = importlib.util.find_spec("foxglove") is not None
    except (ImportError, ValueError):  # a module entry of None (blocked) raises ValueError
        found = False
    if not found:
        raise ValueError(MISSING_EXTRA)


class LiveView:
    """The service's side of the live view: a bounded queue to the publisher process, and its metrics."""

    def __init__(
        self,
        host: str,
        port: int,
        queue_frames: int,
        metrics: ServiceMetrics | None = None,
        key: str | None = None,
    ) -> None:
        check_available()
        self.host, self.requested_port, self.queue_frames = host, port, queue_frames
        # With API keys: the name of the one key whose streams are published (None: no keys, every stream).
        self.key = key
        self.port: int | None = None  # bound at start()
        self.resolution = 0.0  # metres per pixel of the posted scans: the model's, set once it is loaded
        self._context = multiprocessing.get_context("spawn")  # never fork a process holding runtime threads
        self._queue: Any = None
        self._process: Any = None
        self._published: Any = self._context.RawValue("q", 0)  # written by the publisher only: no lock needed
        registry = metrics.registry if metrics is not None else None
        self.published = Gauge(
            "rafd_live_view_published", "frames published to the Foxglove live view so far", registry=registry
        )
        self.published.set_function(lambda: float(self._published.value))
        self.dropped = Counter(
            "rafd_live_view_dropped",
            "answered frames not published to the live view because its queue was full",
            registry=registry,
        )

    @classmethod
    def from_settings(
        cls, settings: Settings, metrics: ServiceMetrics | None = None, key_names: tuple[str, ...] = ()
    ) -> LiveView | None:
        """The live view the settings ask for (None when RAFD_FOXGLOVE_PORT is unset); ValueError without the extra,
        or when the key it shows is not one of the API keys configured (`key_names`), or keys are configured and it
        names none (the view has no authentication: it must not show every key's streams to whoever connects)."""
        if settings.foxglove_port is None:
            return None
        key = settings.foxglove_key
        if key_names and key is None:
            raise ValueError(
                "with API keys the live view shows the streams of one key only: name it with RAFD_FOXGLOVE_KEY "
                "(--foxglove-key, the key's NAME); its WebSocket has no authentication, so whoever reaches "
                "RAFD_FOXGLOVE_HOST:RAFD_FOXGLOVE_PORT sees that key's streams"
            )
        if key is not None and key not in key_names:
            raise ValueError(
                "RAFD_FOXGLOVE_KEY names no configured API key"
                + ("" if key_names else " (no API keys are configured: leave it unset to show every stream)")
            )
        return cls(settings.foxglove_host, settings.foxglove_port, settings.foxglove_queue_frames, metrics, key)

    def start(self) -> None:
        """Start the publisher process and its server; RuntimeError with its reason when it cannot (port taken)."""
        self._queue = self._context.Queue(maxsize=self.queue_frames)
        ours, theirs = self._context.Pipe(duplex=False)
        self._process = self._context.Process(
            target=publish_forever,
            args=(self.host, self.requested_port, self._queue, theirs, self._published),
            name="rafd-live-view",
            daemon=True,
        )
        self._process.start()
        theirs.close()
        if not ours.poll(START_TIMEOUT_S):
            self.stop()
            raise RuntimeError(f"the live view's publisher did not start within {START_TIMEOUT_S:.0f} s")
        status, value = ours.recv()
        ours.close()
        if status != "ready":
            self.stop()
            raise RuntimeError(f"the live view could not start: {value}")
        self.port = int(value)
        log.info(
            "live view: Foxglove WebSocket server on ws://%s:%d (one topic prefix per stream)", self.host, self.port
        )

    def offer(self, answer: dict[str, Any], decoded: DecodedFrame, caller: str | None = None) -> None:
        """Queue one answered frame for publishing; never blocks (a full queue drops it and counts the drop). With
        API keys only the shown key's frames (`caller`: the key's name) are published; the rest never leave here."""
        if caller != self.key:
            return
        if self._queue is None:
            self.dropped.inc()
            return
        try:
            covered = decoded.covered  # the square detected over: shown as the scan and as the 3D grid
            self._queue.put_nowait((answer, covered, covered, decoded.posted_size, self.resolution))
        except queue.Full:
            self.dropped.inc()

    def stop(self) -> None:
        if self._process is not None:
            with contextlib.suppress(queue.Full, ValueError, OSError):
                self._queue.put(None, timeout=1.0)
            self._process.join(timeout=10.0)
            if self._process.is_alive():
                self._process.terminate()
                self._process.join(timeout=5.0)
            self._process = None
        if self._queue is not None:
            self._queue.cancel_join_thread()  # frames still queued are not published: do not wait on them
            self._queue.close()
            self._queue = None


# ----------------------------------------------------------------------------- the publisher process
def publish_forever(host: str, port: int, frames: Any, status: Connection, published: Any) -> None:
    """The publisher process: a foxglove WebSocket server, fed from `frames` until None arrives."""
    with contextlib.suppress(OSError):
        os.nice(PUBLISHER_NICENESS)
    try:
        import foxglove

        context = foxglove.Context()  # its own: nothing else logs to the live view
        server = foxglove.start_server(name="rafd", host=host, port=port, context=context)
    except Exception as error:  # a port taken, a missing library: said to the service, which stops
        status.send(("error", f"{type(error).__name__}: {error}"))
        return
    status.send(("ready", server.port))
    status.close()
    streams: OrderedDict[str, Any] = OrderedDict()  # stream id -> RadarChannels
    try:
        while True:
            item = frames.get()
            if item is None:
                return
            try:
                publish(context, streams, *item)
                published.value += 1
            except Exception:  # a frame that cannot be drawn must not end the live view
                log.exception("live view: frame not published")
    finally:
        server.stop()


def publish(
    context: Any,
    streams: OrderedDict[str, Any],
    answer: dict[str, Any],
    view: Any,
    crop: Any,
    posted_size: int,
    resolution: float,
) -> None:
    """One answered frame on its stream's channels (made on its first frame; the least recent closed beyond
    MAX_STREAM_CHANNELS)."""
    import cv2

    from rafd.viz.mcap import RadarChannels, frame_from_answer

    stream_id = str(answer["stream_id"])
    channels = streams.get(stream_id)
    if channels is None:
        channels = streams[stream_id] = RadarChannels(context, prefix=f"/{stream_id}")
        while len(streams) > MAX_STREAM_CHANNELS:
            _, oldest = streams.popitem(last=False)
            oldest.close()
    streams.move_to_end(stream_id)
    ok, png = cv2.imencode(".png", view)
    if not ok:
        raise ValueError("the scan could not be encoded as PNG")
    side = int(view.shape[0])
    offset = (int(posted_size) - side) // 2
    frame = frame_from_answer(
        answer,
        png.tobytes(),
        side,
        resolution,
        crop,
        max(0, round(float(answer["timestamp"]) * 1e9)),  # foxglove times are unsigned
        scan_offset=offset,
        meaningful_flow_of=view,
    )
    channels.log(frame)
