"""Foxglove / MCAP logs of a radar detection run: written with foxglove-sdk in Foxglove's standard schemas.

Topics (every message stamped with the scan's own time, so the file replays at the sensor's rate):

    /radar/scan                 foxglove.CompressedImage   the scan as PNG (Image panel)
    /radar/scan/grid            foxglove.Grid              what was detected over as a uint8 `intensity` grid in
                                                           frame `radar`, so the 3D panel shows returns under boxes
    /tf                         foxglove.FrameTransform    ego pose: `world` -> `radar` (x right, y forward, z up)
    /radar/detections           foxglove.SceneUpdate       one cube per box (centre, size, yaw), score and #track
    /radar/detections/image     foxglove.ImageAnnotations  box outlines and scores on /radar/scan
    /radar/flow                 foxglove.SceneUpdate       one arrow per moving valid flow cell (true length, metres)
    /radar/velocity             foxglove.SceneUpdate       one arrow per box with a velocity: its motion in 1 s
    /radar/ground_truth         foxglove.SceneUpdate       ground-truth cubes (only when labels exist)
    /radar/ground_truth/image   foxglove.ImageAnnotations  ground-truth outlines on /radar/scan

Each SceneUpdate first deletes everything older on its topic, so a frame shows exactly its own boxes.
`RadarChannels` holds these channels on any foxglove Context: an MCAP file (`RadarMcapLog`), or the service's live
view (service/pipeline/live.py: a WebSocket server, one topic prefix per stream, the same channels and schemas).
`frame_from_answer` turns one /detect answer into a LoggedFrame (rafd client and the live view).
Needs foxglove-sdk (the `logs` extra; the live view's `live` extra; reading back: mcap + mcap-protobuf-support):
import this module only when a log or the live view is asked for.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import foxglove
import numpy as np
from foxglove import channels
from foxglove.mcap import MCAPWriter
from foxglove.messages import (
    ArrowPrimitive,
    Color,
    CompressedImage,
    CubePrimitive,
    FrameTransform,
    Grid,
    ImageAnnotations,
    KeyValuePair,
    PackedElementField,
    PackedElementFieldNumericType,
    Point2,
    PointsAnnotation,
    PointsAnnotationType,
    Pose,
    Quaternion,
    SceneEntity,
    SceneEntityDeletion,
    SceneEntityDeletionType,
    SceneUpdate,
    TextAnnotation,
    TextPrimitive,
    Timestamp,
    Vector2,
    Vector3,
)

FRAME_WORLD = "world"
FRAME_RADAR = "radar"
FRAME_IMAGE = "radar_image"
BOX_HEIGHT_M = 1.6  # radar boxes are 2-D: drawn as 1.6 m tall cubes standing on the ground
TOPICS = {
    "scan": "/radar/scan",
    "grid": "/radar/scan/grid",
    "tf": "/tf",
    "detections": "/radar/detections",
    "detections_image": "/radar/detections/image",
    "flow": "/radar/flow",
    "velocity": "/radar/velocity",
    "truth": "/radar/ground_truth",
    "truth_image": "/radar/ground_truth/image",
}
_PRED_RGBA = (1.0, 0.15, 0.1, 0.55)
_TRUTH_RGBA = (0.1, 0.9, 0.2, 0.35)
_FLOW_RGBA = (1.0, 0.9, 0.1, 1.0)
_VELOCITY_RGBA = (0.15, 0.65, 1.0, 1.0)


@dataclass(frozen=True, eq=False)
class LoggedFrame:
    """One radar frame with what the model said about it; metres in the frame's ego frame (x right, y forward)."""

    timestamp_ns: int  # the scan's time, UNIX nanoseconds
    scan_png: bytes  # the scan as PNG (what was posted / what the model's crop was cut from)
    scan_size: int  # pixels per side of that scan, radar at (S/2, S/2)
    resolution: float  # metres per pixel
    crop: tuple[int, int]  # (offset px, side px) of the model's crop in the scan
    crop_pixels: np.ndarray  # uint8 [side, side]: the crop itself (for the 3D grid)
    pose: np.ndarray  # [3] world pose of the radar (x, y, yaw)
    boxes: np.ndarray  # [N, 5] (x, y, width, length, yaw)
    scores: np.ndarray  # [N]
    classes: list[str]  # [N]
    polygons: np.ndarray  # [N, 4, 2] corner pixels (u, v) in the scan
    flow_heads: np.ndarray | None = None  # [P, 2] metres: cell centres now
    flow_motions: np.ndarray | None = None  # [P, 2] metres moved since the previous frame
    truth_boxes: np.ndarray | None = None  # [M, 5]; None = no labels
    truth_polygons: np.ndarray | None = None  # [M, 4, 2] scan pixels
    track_ids: tuple[str, ...] = ()  # [N] each box's track (the answer's track_id)
    velocities: np.ndarray | None = None  # [N, 2] m/s ground velocity, ego axes; NaN where not measured


def _timestamp(nanoseconds: int) -> Timestamp:
    return Timestamp(sec=int(nanoseconds) // 1_000_000_000, nsec=int(nanoseconds) % 1_000_000_000)


def _yaw_quaternion(yaw: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0))


def _colour(rgba: tuple[float, float, float, float]) -> Color:
    return Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])


class RadarChannels:
    """The radar topics (TOPICS, each under `prefix`) on a foxglove Context; log(frame) writes one frame on all."""

    def __init__(self, context: foxglove.Context, prefix: str = "") -> None:
        self._context, self.prefix = context, prefix.rstrip("/")
        self._scan = channels.CompressedImageChannel(self.topic("scan"), context=context)
        self._grid = channels.GridChannel(self.topic("grid"), context=context)
        self._tf = channels.FrameTransformChannel(self.topic("tf"), context=context)
        self._detections = channels.SceneUpdateChannel(self.topic("detections"), context=context)
        self._detections_image = channels.ImageAnnotationsChannel(self.topic("detections_image"), context=context)
        self._flow = channels.SceneUpdateChannel(self.topic("flow"), context=context)
        self._velocity = channels.SceneUpdateChannel(self.topic("velocity"), context=context)
        # created on the first labelled frame
        self._truth: channels.SceneUpdateChannel | None = None
        self._truth_image: channels.ImageAnnotationsChannel | None = None
        self.frames = 0

    def topic(self, key: str) -> str:
        return self.prefix + TOPICS[key]

    def log(self, frame: LoggedFrame) -> None:
        """Log one frame on every topic (flow only when given, ground truth only when labelled)."""
        time_ns = int(frame.timestamp_ns)
        stamp = _timestamp(time_ns)
        self._scan.log(
            CompressedImage(timestamp=stamp, frame_id=FRAME_IMAGE, data=frame.scan_png, format="png"), log_time=time_ns
        )
        self._grid.log(_grid(frame, stamp), log_time=time_ns)
        self._tf.log(_transform(frame.pose, stamp), log_time=time_ns)
        tracks = [f" #{track_id.rsplit('-', 1)[-1]}" for track_id in frame.track_ids] or [""] * len(frame.classes)
        labels = [f"{c} {s:.2f}{t}" for c, s, t in zip(frame.classes, np.asarray(frame.scores, np.float64), tracks)]
        self._detections.log(_cubes(frame.boxes, labels, "pred", _PRED_RGBA, stamp), log_time=time_ns)
        self._detections_image.log(_outlines(frame.polygons, labels, _PRED_RGBA, stamp), log_time=time_ns)
        if frame.flow_heads is not None and frame.flow_motions is not None:
            self._flow.log(_arrows(frame.flow_heads, frame.flow_motions, stamp), log_time=time_ns)
        if frame.velocities is not None:  # each box's motion in the next second, from its centre
            moving = np.isfinite(frame.velocities).all(axis=1)
            tips = frame.boxes[moving, :2] + frame.velocities[moving]
            self._velocity.log(
                _arrows(tips, frame.velocities[moving], stamp, "velocity", _VELOCITY_RGBA), log_time=time_ns
            )
        if frame.truth_boxes is not None:
            if self._truth is None or self._truth_image is None:  # both or neither
                self._truth = channels.SceneUpdateChannel(self.topic("truth"), context=self._context)
                self._truth_image = channels.ImageAnnotationsChannel(self.topic("truth_image"), context=self._context)
            truth_polygons = frame.truth_polygons if frame.truth_polygons is not None else np.zeros((0, 4, 2))
            names = ["truth"] * len(frame.truth_boxes)
            self._truth.log(_cubes(frame.truth_boxes, names, "truth", _TRUTH_RGBA, stamp), log_time=time_ns)
            self._truth_image.log(
                _outlines(truth_polygons, [""] * len(truth_polygons), _TRUTH_RGBA, stamp), log_time=time_ns
            )
        self.frames += 1

    def close(self) -> None:
        """Close the channels (a live viewer sees them unadvertised)."""
        for channel in (
            self._scan,
            self._grid,
            self._tf,
            self._detections,
            self._detections_image,
            self._flow,
            self._velocity,
        ):
            channel.close()
        for labels in (self._truth, self._truth_image):
            if labels is not None:
                labels.close()


class RadarMcapLog:
    """An MCAP file of one radar stream. Use as a context manager; write(frame) per frame in time order."""

    def __init__(self, path: str | Path, allow_overwrite: bool = True) -> None:
        self.path = Path(path)
        if not self.path.parent.is_dir():
            raise FileNotFoundError(f"folder of the MCAP file {self.path} does not exist")
        self._context = foxglove.Context()  # our own: channels of other logs in this process stay apart
        self._writer: MCAPWriter | None = foxglove.open_mcap(
            self.path, allow_overwrite=allow_overwrite, context=self._context
        )
        self._channels = RadarChannels(self._context)

    @property
    def frames(self) -> int:
        return self._channels.frames

    def __enter__(self) -> RadarMcapLog:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def write_metadata(self, name: str, values: dict[str, object]) -> None:
        """A Metadata record (e.g. the run: sequence, stream, model), values as text."""
        if self._writer is None:
            raise RuntimeError(f"{self.path} is closed")
        self._writer.write_metadata(name, {str(k): str(v) for k, v in values.items()})

    def write(self, frame: LoggedFrame) -> None:
        """Log one frame on every topic (flow only when given, ground truth only when labelled)."""
        if self._writer is None:
            raise RuntimeError(f"{self.path} is closed")
        self._channels.log(frame)


def frame_from_answer(
    answer: dict[str, Any],
    scan_png: bytes,
    scan_size: int,
    resolution: float,
    crop_pixels: np.ndarray,
    timestamp_ns: int,
    scan_offset: int = 0,
    truth_boxes: np.ndarray | None = None,
    truth_polygons: np.ndarray | None = None,
    min_flow_m: float = 0.05,
    meaningful_flow_of: np.ndarray | None = None,
    validity: np.ndarray | None = None,
) -> LoggedFrame:
    """One /detect answer -> LoggedFrame (boxes, polygons and flow as the service answered them).

    `scan_png` is a square scan centred on the radar, `scan_size` px a side, whose top-left corner is the posted
    scan's pixel (`scan_offset`, `scan_offset`): the posted scan itself (offset 0) or its centre (the live view).
    Flow cells moving less than `min_flow_m` get no arrow; with `meaningful_flow_of` (the scan as uint8 pixels),
    neither do cells without returns that are not near a box (rafd.viz.flow_cells.meaningful_cells); with `validity`
    [Hf, Wf] of the flow grid (rafd.viz.answer.answer_validity) only cells reaching FLOW_VALID_MIN get one, and
    without it only the cells the answer's own flow `validity` marks valid (answer_valid_cells)."""
    from rafd.viz.answer import flow_arrows  # opencv: loaded with the picture code
    from rafd.viz.flow_cells import NEAR_BOX_M, meaningful_cells, valid_cells

    covered = answer["input"]["covered"]  # the square detected over (the whole scan, or within the range asked)
    offset, side = covered["offset_px"], covered["side_px"]
    boxes = np.array(
        [[b[k] for k in ("x", "y", "width", "length", "yaw")] for b in answer["boxes"]], dtype=np.float64
    ).reshape(-1, 5)
    polygons = np.array([b["polygon"] for b in answer["boxes"]], dtype=np.float64).reshape(-1, 4, 2) - scan_offset
    heads = motions = None
    if answer.get("flow"):
        keep = None
        if meaningful_flow_of is not None:
            grid = answer["flow"]["grid"]
            keep = meaningful_cells(
                meaningful_flow_of,
                (grid["height"], grid["width"]),
                grid["stride_px"],
                (grid["origin_px"][0] - scan_offset, grid["origin_px"][1] - scan_offset),
                polygons.mean(axis=1) if len(polygons) else None,
                NEAR_BOX_M / resolution,
            )
        grid = answer["flow"]["grid"]
        valid = valid_cells(validity, (int(grid["height"]), int(grid["width"])))
        if valid is None:
            valid = answer_valid_cells(answer["flow"])
        if valid is not None:
            keep = valid if keep is None else keep & valid
        heads_px, motions = flow_arrows(answer["flow"], min_m=min_flow_m, keep=keep)
        posted_half = answer["input"]["posted_size"] / 2.0
        heads = np.stack([(heads_px[:, 0] - posted_half) * resolution, (posted_half - heads_px[:, 1]) * resolution], -1)
    return LoggedFrame(
        timestamp_ns=int(timestamp_ns),
        scan_png=scan_png,
        scan_size=scan_size,
        resolution=resolution,
        crop=(offset - scan_offset, side),
        crop_pixels=crop_pixels,
        pose=np.array([answer["pose"][k] for k in ("x", "y", "yaw")], dtype=np.float64),
        boxes=boxes,
        scores=np.array([b["score"] for b in answer["boxes"]], dtype=np.float64),
        classes=[b["class"] for b in answer["boxes"]],
        polygons=polygons,
        flow_heads=heads,
        flow_motions=motions,
        truth_boxes=truth_boxes,
        truth_polygons=truth_polygons,
        track_ids=tuple(b["track_id"] for b in answer["boxes"]),
        velocities=np.array(
            [
                [b["velocity"]["x"], b["velocity"]["y"]] if b.get("velocity") else [np.nan, np.nan]
                for b in answer["boxes"]
            ],
            dtype=np.float64,
        ).reshape(-1, 2),
    )


def answer_valid_cells(flow: dict[str, Any]) -> np.ndarray | None:
    """[Hf, Wf] bool: the cells of an answer's flow whose `validity` (in the flow's `encoding`: nested lists or
    base64 float16, like its `values`) reaches its `validity_min`; None for an answer without validity (from a
    service before it)."""
    from rafd.viz.answer import decode_validity

    values = decode_validity(flow)
    if values is None:
        return None
    return values >= float(flow["validity_min"])


def _transform(pose: np.ndarray, stamp: Timestamp) -> FrameTransform:
    return FrameTransform(
        timestamp=stamp,
        parent_frame_id=FRAME_WORLD,
        child_frame_id=FRAME_RADAR,
        translation=Vector3(x=float(pose[0]), y=float(pose[1]), z=0.0),
        rotation=_yaw_quaternion(float(pose[2])),
    )


def _grid(frame: LoggedFrame, stamp: Timestamp) -> Grid:
    """The crop as a Grid in the radar frame: row 0 = the crop's bottom row (smallest y), 1 byte per cell."""
    offset, side = frame.crop
    half = frame.scan_size / 2.0
    corner = Vector3(x=(offset - half) * frame.resolution, y=(half - offset - side) * frame.resolution, z=0.0)
    cells = np.ascontiguousarray(np.asarray(frame.crop_pixels, np.uint8)[::-1])  # [side, side], y up
    return Grid(
        timestamp=stamp,
        frame_id=FRAME_RADAR,
        pose=Pose(position=corner, orientation=_yaw_quaternion(0.0)),
        column_count=side,
        cell_size=Vector2(x=frame.resolution, y=frame.resolution),
        row_stride=side,
        cell_stride=1,
        fields=[PackedElementField(name="intensity", offset=0, type=PackedElementFieldNumericType.Uint8)],
        data=cells.tobytes(),
    )


def _cubes(boxes: np.ndarray, labels: list[str], prefix: str, rgba: tuple, stamp: Timestamp) -> SceneUpdate:
    """[N, 5] boxes -> SceneUpdate: delete the older entities, then one cube (+ its label) per box."""
    entities = []
    for k, (box, label) in enumerate(zip(np.asarray(boxes, np.float64).reshape(-1, 5), labels)):
        x, y, width, length, yaw = (float(v) for v in box)
        centre = Pose(position=Vector3(x=x, y=y, z=BOX_HEIGHT_M / 2), orientation=_yaw_quaternion(yaw))
        cube = CubePrimitive(pose=centre, size=Vector3(x=width, y=length, z=BOX_HEIGHT_M), color=_colour(rgba))
        above = Pose(position=Vector3(x=x, y=y, z=BOX_HEIGHT_M + 0.5), orientation=_yaw_quaternion(0.0))
        texts = (
            [
                TextPrimitive(
                    pose=above,
                    billboard=True,
                    font_size=14.0,
                    scale_invariant=True,
                    color=_colour((*rgba[:3], 1.0)),
                    text=label,
                )
            ]
            if label
            else []
        )
        entities.append(
            SceneEntity(
                timestamp=stamp,
                frame_id=FRAME_RADAR,
                id=f"{prefix}-{k}",
                frame_locked=True,
                cubes=[cube],
                texts=texts,
                metadata=[KeyValuePair(key="label", value=label)],
            )
        )
    return SceneUpdate(
        deletions=[SceneEntityDeletion(timestamp=stamp, type=SceneEntityDeletionType.All, id="")], entities=entities
    )


def _outlines(polygons: np.ndarray, labels: list[str], rgba: tuple, stamp: Timestamp) -> ImageAnnotations:
    """[N, 4, 2] scan pixels -> ImageAnnotations: a closed outline per box, its label above the top corner."""
    points, texts = [], []
    for polygon, label in zip(np.asarray(polygons, np.float64).reshape(-1, 4, 2), labels):
        points.append(
            PointsAnnotation(
                timestamp=stamp,
                type=PointsAnnotationType.LineLoop,
                points=[Point2(x=float(u), y=float(v)) for u, v in polygon],
                outline_color=_colour((*rgba[:3], 1.0)),
                thickness=1.5,
            )
        )
        if label:
            top = polygon[np.argmin(polygon[:, 1])]
            texts.append(
                TextAnnotation(
                    timestamp=stamp,
                    position=Point2(x=float(top[0]), y=float(top[1]) - 3.0),
                    text=label,
                    font_size=12.0,
                    text_color=_colour((*rgba[:3], 1.0)),
                    background_color=_colour((0.0, 0.0, 0.0, 0.6)),
                )
            )
    return ImageAnnotations(points=points, texts=texts)


def _arrows(
    heads: np.ndarray,
    motions: np.ndarray,
    stamp: Timestamp,
    name: str = "flow",
    rgba: tuple[float, float, float, float] = _FLOW_RGBA,
) -> SceneUpdate:
    """Motions -> one entity of arrows from where each thing was to its head (true length): the flow's cells, or the
    boxes' velocities over one second."""
    arrows = []
    heads, motions = np.asarray(heads, np.float64).reshape(-1, 2), np.asarray(motions, np.float64).reshape(-1, 2)
    for head, motion in zip(heads, motions):
        length = float(np.hypot(*motion))
        if length <= 0:
            continue
        tail = head - motion
        head_length = min(0.3 * length, 0.4)
        arrows.append(
            ArrowPrimitive(
                pose=Pose(
                    position=Vector3(x=float(tail[0]), y=float(tail[1]), z=0.1),
                    orientation=_yaw_quaternion(math.atan2(motion[1], motion[0])),
                ),
                shaft_length=length - head_length,
                shaft_diameter=0.08,
                head_length=head_length,
                head_diameter=0.25,
                color=_colour(rgba),
            )
        )
    entity = SceneEntity(timestamp=stamp, frame_id=FRAME_RADAR, id=name, frame_locked=True, arrows=arrows)
    return SceneUpdate(
        deletions=[SceneEntityDeletion(timestamp=stamp, type=SceneEntityDeletionType.All, id="")], entities=[entity]
    )
