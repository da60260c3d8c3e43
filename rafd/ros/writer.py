"""Write a rosbag2 bag that is complete or absent: it is written under a temporary name beside OUT
(`.OUT.<random>.partial/OUT`) and moved into place when closed; an error (or an interrupt) removes it, so a bag at OUT
is never half-written. MCAP storage by default (every message's schema embedded: Foxglove, mcap-ros2-support and
`ros2 bag` read it alone), sqlite3 on request.

AnswerBag writes the topics of a run of answers (rafd.ros.answers): /rafd/detections, /rafd/tracks, /rafd/odometry
and /tf per scan, /rafd/scan and /rafd/flow on request, each stamped with the scan's time (message log time and
header stamp alike).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

from rafd.ros import answers, types

STORAGES = ("mcap", "sqlite3")
TOPIC_DETECTIONS = "/rafd/detections"
TOPIC_TRACKS = "/rafd/tracks"
TOPIC_ODOMETRY = "/rafd/odometry"
TOPIC_TF = "/tf"
TOPIC_SCAN = "/rafd/scan"
TOPIC_FLOW = "/rafd/flow"


class BagWriter:
    """A rosbag2 bag at `out`, written under a temporary name and moved into place by close(); abort() (or leaving
    the `with` block with an exception) removes it. FileExistsError when `out` exists. `store`: the types to write
    with (default rafd.ros.types.typestore())."""

    def __init__(self, out: str | Path, storage: str = "mcap", store: Any = None) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer

        if storage not in STORAGES:
            raise ValueError(f"bag storage {storage!r}; one of {', '.join(STORAGES)}")
        self.out = Path(out)
        if self.out.exists():
            raise FileExistsError(f"{self.out} exists; rafd writes a new bag, never over one")
        if not self.out.parent.is_dir():
            raise FileNotFoundError(f"folder of {self.out} does not exist")
        self.work = Path(tempfile.mkdtemp(prefix=f".{self.out.name}.", suffix=".partial", dir=self.out.parent))
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        self.store = store if store is not None else types.typestore()
        self.writer = Writer(self.work / self.out.name, version=Writer.VERSION_LATEST, storage_plugin=plugin)
        self.connections: dict[str, Any] = {}
        self.messages = 0
        try:
            self.writer.open()
        except BaseException:
            shutil.rmtree(self.work, ignore_errors=True)
            raise

    def write(self, topic: str, msgtype: str, stamp_ns: int, message: Any) -> None:
        """One message on `topic` logged at `stamp_ns`."""
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=self.store)
        data = self.store.serialize_cdr(message, msgtype)
        self.writer.write(self.connections[topic], int(stamp_ns), data)
        self.messages += 1

    def close(self) -> Path:
        """Finish the bag and move it to `out`."""
        try:
            self.writer.close()
            os.rename(self.work / self.out.name, self.out)  # refuses an `out` made meanwhile
        except BaseException:
            self.abort()
            raise
        shutil.rmtree(self.work, ignore_errors=True)
        return self.out

    def abort(self) -> None:
        """Drop the bag: nothing is left at `out` or beside it."""
        try:
            if self.writer.storage is not None:
                self.writer.abort()
        finally:
            shutil.rmtree(self.work, ignore_errors=True)

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, traceback: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


class AnswerBag:
    """The answers of one stream as ROS 2 messages in a bag (close() to keep it, abort() to drop it)."""

    def __init__(
        self,
        out: str | Path,
        stream_id: str,
        storage: str = "mcap",
        with_scan: bool = False,
        with_flow: bool = False,
        frame_id: str = answers.FRAME_RADAR,
    ) -> None:
        self.bag = BagWriter(out, storage)
        self.stream_id, self.with_scan, self.with_flow, self.frame_id = stream_id, with_scan, with_flow, frame_id
        self.scans = 0

    def write(
        self, answer: dict[str, Any], stamp_ns: int, scan: np.ndarray | None = None, resolution: float | None = None
    ) -> None:
        """One answered scan, stamped `stamp_ns`; `scan` (uint8 [N, N] Cartesian, `resolution` m/px) for /rafd/scan."""
        store, stamp, frame = self.bag.store, int(stamp_ns), self.frame_id
        write = self.bag.write
        write(
            TOPIC_DETECTIONS, types.DETECTIONS, stamp, answers.detections(store, answer, stamp, self.stream_id, frame)
        )
        write(TOPIC_TRACKS, types.TRACKS, stamp, answers.tracks(store, answer, stamp, self.stream_id, frame))
        write(TOPIC_ODOMETRY, types.ODOMETRY, stamp, answers.odometry(store, answer, stamp, frame))
        write(TOPIC_TF, types.TF, stamp, answers.transform(store, answer, stamp, frame))
        if self.with_scan and scan is not None and resolution is not None:
            write(TOPIC_SCAN, types.OCCUPANCY_GRID, stamp, answers.scan_grid(store, scan, resolution, stamp, frame))
        if self.with_flow:
            write(TOPIC_FLOW, types.MARKERS, stamp, answers.flow_markers(store, answer, stamp, frame))
        self.scans += 1

    def close(self) -> Path:
        return self.bag.close()

    def abort(self) -> None:
        self.bag.abort()
