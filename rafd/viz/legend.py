"""What a picture says about itself: the legend naming its colours and the flow arrows' scale in metres, and the
distance bar (opencv)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from rafd.viz.drawing import FLOW_COLOUR, FONT, GT_COLOUR, PRED_COLOUR, TEXT_COLOUR, TRACK_COLOUR, Rect, draw_arrow


@dataclass(frozen=True)
class Legend:
    """What a picture shows: the colours, and how long 1 m of flow is drawn (None: no flow in the picture)."""

    truth: bool = True
    flow_px_per_m: float | None = None  # canvas pixels per metre of motion, the exaggeration included
    flow_scale: float = 1.0  # how many times longer than the true motion arrows are drawn
    font_scale: float = 0.45
    score_threshold: float | None = None  # the threshold boxes were drawn at (stated), None: not stated
    flow_where: str | None = None  # where arrows are drawn when not everywhere (stated)
    velocity_px_per_s: float | None = None  # canvas pixels per metre a box moves in 1 s (None: no velocities)


def _legend_items(legend: Legend) -> list[tuple[str, tuple[int, int, int], str, int]]:
    """(text, colour, sample kind, sample width px)."""
    shown = "score" if legend.score_threshold is None else f"score >= {legend.score_threshold:.2f}, operating threshold"
    items = [(f"prediction ({shown})", PRED_COLOUR, "box", 22)]
    if legend.truth:
        items.append(("ground truth", GT_COLOUR, "box", 22))
    if legend.flow_px_per_m is not None:
        text = "flow, arrow = 1 m" + ("" if legend.flow_scale == 1 else f" (drawn x{legend.flow_scale:g})")
        if legend.flow_where:
            text += f", at {legend.flow_where}"
        items.append((text, FLOW_COLOUR, "arrow", max(8, int(round(legend.flow_px_per_m)))))
    if legend.velocity_px_per_s is not None:
        sample = max(8, int(round(legend.velocity_px_per_s)))
        items.append(("#track, velocity: where in 1 s, trail", TRACK_COLOUR, "arrow", sample))
    return items


def _legend_layout(legend: Legend, width: int) -> tuple[list[tuple[int, int]], int]:
    """Item positions (x, y top-left) flowing left to right and wrapping at `width`, and the total height."""
    line = int(round(24 * legend.font_scale / 0.45))
    positions, x, y = [], 0, 0
    for text, _, _, sample in _legend_items(legend):
        item = sample + 6 + cv2.getTextSize(text, FONT, legend.font_scale, 1)[0][0] + 16
        if x > 0 and x + item > width:
            x, y = 0, y + line
        positions.append((x, y))
        x += item
    return positions, y + line


def legend_height(legend: Legend, width: int) -> int:
    """Pixels a legend needs at this width (its items wrap onto more lines when narrow)."""
    return _legend_layout(legend, width)[1]


def draw_legend(canvas: np.ndarray, origin: tuple[int, int], width: int, legend: Legend) -> int:
    """Draw the legend at origin (x, y) within `width` pixels -> the y just below it."""
    positions, height = _legend_layout(legend, width)
    line = int(round(24 * legend.font_scale / 0.45))
    for (dx, dy), (text, colour, kind, sample) in zip(positions, _legend_items(legend)):
        x, y = origin[0] + dx, origin[1] + dy
        middle = y + line / 2.0
        if kind == "box":
            cv2.rectangle(canvas, (x, y + 5), (x + sample, y + line - 6), colour, 1, cv2.LINE_AA)
        else:
            draw_arrow(canvas, (x, middle), (x + sample, middle), colour, 2)
        baseline = int(middle + cv2.getTextSize(text, FONT, legend.font_scale, 1)[0][1] / 2)
        cv2.putText(canvas, text, (x + sample + 6, baseline), FONT, legend.font_scale, TEXT_COLOUR, 1, cv2.LINE_AA)
    return origin[1] + height


SCALE_BAR_GAP_PX = 4  # clear pixels between the scale bar (ticks and outline included) and its label


def scale_bar_layout(
    canvas_shape: tuple[int, ...], px_per_m: float, font_scale: float = 0.45
) -> tuple[int, Rect, Rect]:
    """(metres, bar rect, label rect) of the distance bar, bottom left: the longest of 1, 2, 5, 10, 20, 50 m that
    fits a quarter of the width; the label above the bar, SCALE_BAR_GAP_PX clear of its ticks and outlines. Rects
    are (x, y, width, height) of the pixels drawn, outlines included."""
    height, width = canvas_shape[0], canvas_shape[1]
    metres = max((m for m in (1, 2, 5, 10, 20, 50) if m * px_per_m <= width / 4), default=1)
    x0, y0 = 10, height - 12
    x1 = int(round(x0 + metres * px_per_m))
    outline = 2  # half the outline's 4 px line width
    bar = (x0 - outline, y0 - 4 - outline, x1 - x0 + 2 * outline + 1, 8 + 2 * outline + 1)
    (text_width, text_height), baseline = cv2.getTextSize(f"{metres} m", FONT, font_scale, 3)
    text_bottom = bar[1] - SCALE_BAR_GAP_PX  # the label's lowest pixel (its outline's) is above this row
    label = (x0 - 1, text_bottom - text_height - baseline - 1, text_width + 2, text_height + baseline + 1)
    return metres, bar, label


def draw_scale_bar(canvas: np.ndarray, px_per_m: float, font_scale: float = 0.45) -> None:
    """A distance bar, bottom left (scale_bar_layout): its label never touches the bar."""
    metres, bar, label = scale_bar_layout(canvas.shape, px_per_m, font_scale)
    x0, y0 = 10, canvas.shape[0] - 12
    x1 = int(round(x0 + metres * px_per_m))
    for colour, thickness in (((0, 0, 0), 4), (TEXT_COLOUR, 2)):  # outlined: readable on bright returns too
        cv2.line(canvas, (x0, y0), (x1, y0), colour, thickness)
        for x in (x0, x1):
            cv2.line(canvas, (x, y0 - 4), (x, y0 + 4), colour, thickness)
    baseline_y = label[1] + label[3] - cv2.getTextSize(f"{metres} m", FONT, font_scale, 3)[1] - 1
    for colour, thickness in (((0, 0, 0), 3), (TEXT_COLOUR, 1)):
        cv2.putText(canvas, f"{metres} m", (x0, baseline_y), FONT, font_scale, colour, thickness, cv2.LINE_AA)
