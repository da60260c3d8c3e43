"""The picture of one /detect answer (rafd-client): what was detected over, beside an overview and a legend.

    +--------------------------------------+---------------------+
    | what was detected over (the whole    | whole posted scan,  |
    | scan, or the square around the radar | that area outlined  |
    | the range asked), zoomed to fit:     |---------------------|
    | predictions with their scores,       | legend: prediction, |
    | ground truth, flow arrows, a         | ground truth, flow  |
    | distance bar                         | arrow = 1 m         |
    |                                      | status of the answer|
    +--------------------------------------+---------------------+

A small area is zoomed by an integer factor (crisp pixels), a whole scan shrunk to fit. Given the answer's flow
validity (decode_validity) the arrows are drawn only where the flow was measured over the network's whole search
range.
"""

from __future__ import annotations

import base64
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from rafd import flow_png
from rafd.geometry import RADIATE_RESOLUTION
from rafd.viz.drawing import (
    FLOW_COLOUR,
    FONT,
    GT_COLOUR,
    PANEL_COLOUR,
    PRED_COLOUR,
    TEXT_COLOUR,
    TRACK_COLOUR,
    draw_arrow,
    draw_polygons,
    draw_scores,
)
from rafd.viz.flow_cells import valid_cells
from rafd.viz.legend import Legend, draw_legend, draw_scale_bar

FLOW_SCALES = (1.0, 2.0, 5.0, 10.0)  # arrow exaggerations tried, smallest first
MIN_ARROW_PX_PER_M = 24.0  # 1 m of motion must be at least this long on screen


@dataclass(frozen=True)
class AnswerView:
    view_px: int = 768  # a small area: the largest integer zoom that fits (at least 1x); a larger one shrunk to fit
    panel_px: int = 300  # width of the side panel
    flow_step: int = 2  # draw every n-th flow cell
    flow_scale: float | None = None  # arrows / true motion; None: the smallest of FLOW_SCALES giving 24 px per metre
    min_flow_m: float = 0.05  # cells moving less are not drawn
    font_scale: float = 0.45

    def __post_init__(self) -> None:
        if self.view_px < 1 or self.panel_px < 120 or self.flow_step < 1:
            raise ValueError(f"need view_px >= 1, panel_px >= 120, flow_step >= 1; got {self}")
        if self.flow_scale is not None and not self.flow_scale > 0:
            raise ValueError(f"flow_scale must be positive, got {self.flow_scale}")


def decode_flow(flow: dict[str, Any]) -> np.ndarray:
    """The answer's flow (list or base64 float16 encoding) -> float64 [2, Hf, Wf] metres (x right, y forward)."""
    shape = tuple(int(n) for n in flow["shape"])
    if flow["encoding"] == "png":
        return flow_png.decode_flow(base64.b64decode(flow["values"]), (shape[0], shape[1], shape[2]))
    if flow["encoding"] == "base64-float16":
        values = np.frombuffer(base64.b64decode(flow["values"]), dtype="<f2").reshape(shape)
    else:
        values = np.asarray(flow["values"], dtype=np.float64).reshape(shape)
    return values.astype(np.float64)


def decode_validity(flow: dict[str, Any]) -> np.ndarray | None:
    """The answer's flow validity (in the values' encoding) -> float64 [Hf, Wf]; None when the answer carries none."""
    if flow.get("validity") is None:
        return None
    shape = (int(flow["grid"]["height"]), int(flow["grid"]["width"]))
    if flow["encoding"] == "png":
        return flow_png.decode_steps(base64.b64decode(flow["validity"]), (shape[0], shape[1]))
    if flow["encoding"] == "base64-float16":
        return np.frombuffer(base64.b64decode(flow["validity"]), dtype="<f2").reshape(shape).astype(np.float64)
    return np.asarray(flow["validity"], dtype=np.float64).reshape(shape)


def flow_arrows(
    flow: dict[str, Any], step: int = 1, min_m: float = 0.0, keep: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Cells of the answer's flow grid -> (heads [P, 2] posted pixels of the cell centres, motions [P, 2] metres
    x right / y forward) for every `step`-th cell moving more than `min_m` (and marked in `keep` [Hf, Wf])."""
    values = decode_flow(flow)  # [2, Hf, Wf]
    grid = flow["grid"]
    rows, cols = np.meshgrid(np.arange(grid["height"]), np.arange(grid["width"]), indexing="ij")  # [Hf, Wf]
    u = grid["origin_px"][0] + (cols + 0.5) * grid["stride_px"]
    v = grid["origin_px"][1] + (rows + 0.5) * grid["stride_px"]
    heads = np.stack([u, v], -1)[::step, ::step].reshape(-1, 2)  # [P, 2]
    motions = np.moveaxis(values, 0, -1)[::step, ::step].reshape(-1, 2)  # [P, 2]
    moving = np.hypot(motions[:, 0], motions[:, 1]) > min_m
    if keep is not None:
        moving &= np.asarray(keep, dtype=bool)[::step, ::step].reshape(-1)
    return heads[moving], motions[moving]


def track_number(track_id: str) -> str:
    """A track id's number within its chain (CHAIN-N -> N): what a picture labels a box with."""
    return track_id.rsplit("-", 1)[-1]


def _flow_scale(px_per_m: float, chosen: float | None) -> float:
    if chosen is not None:
        return float(chosen)
    return next((s for s in FLOW_SCALES if s * px_per_m >= MIN_ARROW_PX_PER_M), FLOW_SCALES[-1])


def _status_lines(answer: dict[str, Any], title: str | None) -> list[str]:
    warming = " (warming up)" if answer.get("warming_up") else ""
    return ([title] if title else []) + [
        f"t = {answer['timestamp']:.3f} s",
        f"frames {answer['frames_used']}/{answer['num_frames']}{warming}",
        f"pose: {answer['pose_source']}",
        f"{len(answer['boxes'])} boxes, model {answer['timing']['model_ms']:.0f} ms",
    ]


def draw_answer(
    scan: np.ndarray,
    answer: dict[str, Any],
    truth_polygons: np.ndarray | None = None,
    resolution: float = RADIATE_RESOLUTION,
    view: AnswerView = AnswerView(),
    title: str | None = None,
    validity: np.ndarray | None = None,
    trails: Mapping[str, np.ndarray] | None = None,
) -> np.ndarray:
    """The posted scan uint8 [N, N], its /detect answer and (optional) ground-truth polygons [M, 4, 2] in posted
    pixels -> BGR uint8 picture [H, W, 3] (layout in the module docstring). With `validity` [Hf, Wf] of the flow
    grid (answer_validity) flow arrows only where it reaches FLOW_VALID_MIN. Every box's label carries its track's
    number, and its velocity is drawn as an arrow of where it will be in 1 s; `trails`: track id -> [P, 2] earlier
    centres of that track in posted pixels of this scan (the client's Trails), drawn as a line."""
    scan = np.asarray(scan)
    posted = int(answer["input"]["posted_size"])
    covered = answer["input"]["covered"]  # the square detected over
    size, offset = int(covered["side_px"]), int(covered["offset_px"])
    if scan.dtype != np.uint8 or scan.ndim != 2 or scan.shape != (posted, posted):
        raise ValueError(f"the scan must be the posted uint8 [{posted}, {posted}] image, got {scan.dtype} {scan.shape}")
    zoom: float = max(1, view.view_px // size) if size <= view.view_px else view.view_px / size
    side = int(round(size * zoom))
    area = scan[offset : offset + size, offset : offset + size]
    shrink = cv2.INTER_NEAREST if zoom >= 1 else cv2.INTER_AREA
    canvas = cv2.resize(cv2.cvtColor(area, cv2.COLOR_GRAY2BGR), (side, side), interpolation=shrink)

    def to_view(uv: np.ndarray) -> np.ndarray:
        """Posted continuous pixels -> view canvas pixels."""
        return (np.asarray(uv, dtype=np.float64) - offset) * zoom

    px_per_m = zoom / resolution
    flow_scale = _flow_scale(px_per_m, view.flow_scale)
    if answer.get("flow"):
        grid = answer["flow"]["grid"]
        keep = valid_cells(validity, (int(grid["height"]), int(grid["width"])))
        heads, motions = flow_arrows(answer["flow"], view.flow_step, view.min_flow_m, keep)
        for head, motion in zip(to_view(heads), motions):
            tail = head - flow_scale * px_per_m * np.array([motion[0], -motion[1]])  # image v points backwards
            draw_arrow(canvas, tuple(tail), tuple(head), FLOW_COLOUR)
    thickness = 2 if zoom >= 3 else 1
    if truth_polygons is not None and len(truth_polygons):
        draw_polygons(canvas, to_view(truth_polygons), GT_COLOUR, 1, thickness)
    predicted = np.array([box["polygon"] for box in answer["boxes"]], dtype=np.float64).reshape(-1, 4, 2)
    draw_polygons(canvas, to_view(predicted), PRED_COLOUR, 1, thickness)
    for track_id, trail in (trails or {}).items():
        if len(trail) > 1 and any(box["track_id"] == track_id for box in answer["boxes"]):
            cv2.polylines(canvas, [np.round(to_view(trail)).astype(np.int32)], False, TRACK_COLOUR, 1, cv2.LINE_AA)
    for box, polygon in zip(answer["boxes"], to_view(predicted)):
        if box.get("velocity"):  # where the box will be in 1 s, at its ground velocity
            centre = polygon.mean(axis=0)
            ahead = centre + px_per_m * np.array([box["velocity"]["x"], -box["velocity"]["y"]])
            draw_arrow(canvas, tuple(centre), tuple(ahead), TRACK_COLOUR)
    draw_scores(
        canvas,
        to_view(predicted),
        np.array([box["score"] for box in answer["boxes"]]),
        PRED_COLOUR,
        view.font_scale,
        suffixes=[f" #{track_number(box['track_id'])}" for box in answer["boxes"]],
    )
    draw_scale_bar(canvas, px_per_m, view.font_scale)

    panel = _side_panel(
        scan,
        answer,
        truth_polygons,
        predicted,
        (offset, size),
        canvas.shape[0],
        view,
        # The flow entry is shown on every frame (a stream's first has no flow): pictures keep one size.
        Legend(
            truth=truth_polygons is not None,
            flow_px_per_m=flow_scale * px_per_m,
            flow_scale=flow_scale,
            font_scale=view.font_scale,
            velocity_px_per_s=px_per_m,
        ),
        f"detected over {size} px, x{zoom:.3g}",
        title,
    )
    height = max(canvas.shape[0], panel.shape[0])
    out = np.full((height, canvas.shape[1] + panel.shape[1], 3), PANEL_COLOUR, np.uint8)
    out[: canvas.shape[0], : canvas.shape[1]] = canvas
    out[: panel.shape[0], canvas.shape[1] :] = panel
    return out


def _side_panel(
    scan: np.ndarray,
    answer: dict[str, Any],
    truth: np.ndarray | None,
    predicted: np.ndarray,
    crop: tuple[int, int],
    min_height: int,
    view: AnswerView,
    legend: Legend,
    caption: str,
    title: str | None,
) -> np.ndarray:
    """Overview of the whole posted scan with the detected area outlined, then the legend, then the answer's
    status."""
    width, margin = view.panel_px, 8
    line = int(round(22 * view.font_scale / 0.45))
    inner = width - 2 * margin
    scale = inner / scan.shape[0]
    overview = cv2.cvtColor(cv2.resize(scan, (inner, inner), interpolation=cv2.INTER_AREA), cv2.COLOR_GRAY2BGR)
    if truth is not None and len(truth):
        draw_polygons(overview, truth, GT_COLOUR, scale)
    draw_polygons(overview, predicted, PRED_COLOUR, scale)
    offset, size = crop
    end = offset + size
    outline = np.array([[[offset, offset], [end, offset], [end, end], [offset, end]]], dtype=np.float64)  # [1, 4, 2]
    draw_polygons(overview, outline, TEXT_COLOUR, scale)
    panel = np.full((max(min_height, 4000), width, 3), PANEL_COLOUR, np.uint8)  # cut to what is used below
    y = margin
    cv2.putText(
        panel, "whole scan, area outlined", (margin, y + line - 6), FONT, view.font_scale, TEXT_COLOUR, 1, cv2.LINE_AA
    )
    y += line
    panel[y : y + inner, margin : margin + inner] = overview
    y += inner + margin
    y = draw_legend(panel, (margin, y), inner, legend) + margin
    for text in [caption, *_status_lines(answer, title)]:
        cv2.putText(panel, text, (margin, y + line - 6), FONT, view.font_scale, TEXT_COLOUR, 1, cv2.LINE_AA)
        y += line
    return panel[: max(min_height, y + margin)]
