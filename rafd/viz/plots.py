"""Pictures for inspection: detections and flow over a radar scan (opencv), precision-recall plots (matplotlib).

Colours are BGR (opencv order, ready for cv2.imwrite): ground truth green, predictions red with
their score, flow arrows yellow (tail where the content was at t-1, head where it is at t). Score labels
never overlap (place_labels); every picture carries a legend naming the colours and the flow arrows' scale
in metres (draw_legend). The service answer's picture (model crop zoomed, side panel) is rafd.viz.answer.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from rafd.flow_validity import FLOW_VALID_MIN
from rafd.geometry import box_polygons_pixels, feature_cell_centres, metres_to_pixels

GT_COLOUR = (0, 255, 0)
PRED_COLOUR = (0, 0, 255)
FLOW_COLOUR = (0, 255, 255)
TEXT_COLOUR = (235, 235, 235)
PANEL_COLOUR = (32, 32, 32)
FONT = cv2.FONT_HERSHEY_SIMPLEX
_SHIFT = 4  # fractional bits for opencv's sub-pixel drawing

Rect = tuple[int, int, int, int]  # (x, y, width, height) in canvas pixels, y down


def _to_cv_points(uv: np.ndarray, upscale: float) -> np.ndarray:
    """[..., 2] continuous pixels (pixel i covers [i, i+1)) -> int32 fixed-point points for opencv (shift=_SHIFT)."""
    # opencv's integer coordinate i is the centre of pixel i, i.e. continuous i + 0.5.
    return np.round((np.asarray(uv) * upscale - 0.5) * (1 << _SHIFT)).astype(np.int32)


def draw_polygons(
    canvas: np.ndarray, polygons: np.ndarray, colour: tuple[int, int, int], upscale: float = 1, thickness: int = 1
) -> None:
    """Outline [N, 4, 2] continuous-pixel polygons in place (scaled by `upscale` onto the canvas)."""
    if len(polygons):
        cv2.polylines(canvas, list(_to_cv_points(polygons, upscale)), True, colour, thickness, cv2.LINE_AA, _SHIFT)


def draw_arrow(
    canvas: np.ndarray,
    tail: tuple[float, float],
    head: tuple[float, float],
    colour: tuple[int, int, int],
    thickness: int = 1,
) -> None:
    """One arrow between continuous canvas points, its head a readable size whatever its length."""
    length = float(np.hypot(head[0] - tail[0], head[1] - tail[1]))
    tip = min(0.4, 5.0 / length) if length > 0 else 0.3
    tail_i, head_i = _to_cv_points(np.array([tail, head], np.float64), 1)
    cv2.arrowedLine(
        canvas,
        tuple(int(t) for t in tail_i),
        tuple(int(h) for h in head_i),
        colour,
        thickness,
        cv2.LINE_AA,
        _SHIFT,
        tip,
    )


# ---------------------------------------------------------------- score labels that do not overlap
def _intersects(a: Rect, b: Rect) -> bool:
    return a[0] < b[0] + b[2] and b[0] < a[0] + a[2] and a[1] < b[1] + b[3] and b[1] < a[1] + a[3]


def place_labels(
    anchors: list[Rect],
    sizes: list[tuple[int, int]],
    bounds: tuple[int, int],
    avoid: Sequence[Rect] = (),
    gap: int = 2,
    max_rings: int = 8,
) -> list[Rect | None]:
    """Greedy placement in the given order (most important first). For each anchor (a box's bounding rect) the
    first free spot for a label of size (w, h): above, below, right of, left of the anchor, then the same four one
    label further out, up to `max_rings` times. Free = inside `bounds` (width, height), clear of `avoid` and of
    every label placed before. None where no spot is free: the caller leaves that label out. The rects returned
    never overlap each other."""
    taken: list[Rect] = list(avoid)
    out: list[Rect | None] = []
    width, height = bounds
    for (ax, ay, aw, ah), (tw, th) in zip(anchors, sizes):
        found = None
        centre_x, centre_y = ax + aw // 2 - tw // 2, ay + ah // 2 - th // 2
        for ring in range(max_rings):
            far_x, far_y = ring * (tw + gap), ring * (th + gap)
            for x, y in (
                (centre_x, ay - gap - th - far_y),
                (centre_x, ay + ah + gap + far_y),
                (ax + aw + gap + far_x, centre_y),
                (ax - gap - tw - far_x, centre_y),
            ):
                rect = (int(x), int(y), int(tw), int(th))
                inside = rect[0] >= 0 and rect[1] >= 0 and rect[0] + tw <= width and rect[1] + th <= height
                if inside and not any(_intersects(rect, other) for other in taken):
                    found = rect
                    break
            if found is not None:
                break
        out.append(found)
        if found is not None:
            taken.append(found)
    return out


def draw_scores(
    canvas: np.ndarray,
    polygons: np.ndarray,
    scores: np.ndarray,
    colour: tuple[int, int, int],
    font_scale: float = 0.4,
    avoid: Sequence[Rect] = (),
) -> list[Rect | None]:
    """Score labels for [N, 4, 2] canvas-pixel polygons, placed best score first and never overlapping (a thin
    leader line joins a label pushed away from its box) -> the label rects in the polygons' order."""
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    if len(polygons) == 0:
        return []
    order = [int(k) for k in np.argsort(-scores, kind="stable")]
    texts = [f"{scores[k]:.2f}" for k in order]
    sizes = []
    for text in texts:
        (tw, th), baseline = cv2.getTextSize(text, FONT, font_scale, 1)
        sizes.append((tw + 2, th + baseline + 2))
    anchors = []
    for k in order:
        low, high = np.floor(polygons[k].min(0)).astype(int), np.ceil(polygons[k].max(0)).astype(int)
        anchors.append((int(low[0]), int(low[1]), int(high[0] - low[0]), int(high[1] - low[1])))
    rects = place_labels(anchors, sizes, (canvas.shape[1], canvas.shape[0]), list(avoid))
    for text, anchor, rect in zip(texts, anchors, rects):
        if rect is None:
            continue
        x, y, tw, th = rect
        label_centre = (x + tw // 2, y + th // 2)
        box_centre = (anchor[0] + anchor[2] // 2, anchor[1] + anchor[3] // 2)
        if (
            abs(label_centre[0] - box_centre[0]) > (anchor[2] + tw) // 2 + 4
            or abs(label_centre[1] - box_centre[1]) > (anchor[3] + th) // 2 + 4
        ):
            cv2.line(canvas, box_centre, label_centre, colour, 1, cv2.LINE_AA)  # pushed away: show whose it is
        cv2.rectangle(canvas, (x, y), (x + tw - 1, y + th - 1), (0, 0, 0), -1)
        cv2.putText(canvas, text, (x + 1, y + th - 3), FONT, font_scale, colour, 1, cv2.LINE_AA)
    out: list[Rect | None] = [None] * len(polygons)
    for position, k in enumerate(order):
        out[k] = rects[position]
    return out


# ---------------------------------------------------------------- legend and scale bar
@dataclass(frozen=True)
class Legend:
    """What a picture shows: the colours, and how long 1 m of flow is drawn (None: no flow in the picture)."""

    truth: bool = True
    flow_px_per_m: float | None = None  # canvas pixels per metre of motion, the exaggeration included
    flow_scale: float = 1.0  # how many times longer than the true motion arrows are drawn
    font_scale: float = 0.45
    score_threshold: float | None = None  # the threshold boxes were drawn at (stated), None: not stated
    flow_where: str | None = None  # where arrows are drawn when not everywhere (stated)


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


# ---------------------------------------------------------------- where the flow means something
RETURNS_PERCENTILE = 95.0  # a cell holds returns when its brightest pixel reaches the image's 95th percentile ...
MIN_RETURN_LEVEL = 60  # ... and at least this grey level (a dark scan's percentile is still noise)
NEAR_BOX_M = 3.0  # cells whose centre is within this of a box centre (predicted or labelled) are drawn too


def meaningful_cells(
    image: np.ndarray,
    shape: tuple[int, int],
    stride: int,
    origin: tuple[float, float] = (0.0, 0.0),
    centres: np.ndarray | None = None,
    near_px: float = 0.0,
) -> np.ndarray:
    """[Hf, Wf] bool: the flow cells worth an arrow. A cell's flow is estimated everywhere, but it means something
    only where the scan has returns to follow or near an object; elsewhere (empty sky, the crop's padded edges) it is
    the network's extrapolation. `image`: the scan the grid lies on (uint8); cell (i, j) covers image pixels
    [origin_u + j*stride, +stride) x [origin_v + i*stride, +stride); `centres`: [N, 2] box centres (u, v) in image
    pixels, cells within `near_px` of one kept whatever their returns."""
    height, width = shape
    pixels = np.asarray(image, dtype=np.float32)
    level = max(float(np.percentile(pixels, RETURNS_PERCENTILE)), float(MIN_RETURN_LEVEL))
    u0, v0 = int(round(origin[0])), int(round(origin[1]))
    keep = np.zeros((height, width), dtype=bool)
    if u0 >= 0 and v0 >= 0:
        block = pixels[v0 : v0 + height * stride, u0 : u0 + width * stride]
        if block.shape == (height * stride, width * stride):
            keep |= block.reshape(height, stride, width, stride).max(axis=(1, 3)) >= level
    if centres is not None and len(centres) and near_px > 0:
        u = origin[0] + (np.arange(width) + 0.5) * stride
        v = origin[1] + (np.arange(height) + 0.5) * stride
        grid = np.stack(np.meshgrid(u, v), -1)  # [Hf, Wf, 2] (u, v)
        distance = np.linalg.norm(grid[:, :, None, :] - np.asarray(centres, np.float64)[None, None], axis=-1)
        keep |= distance.min(axis=-1) <= near_px
    return keep


def valid_cells(validity: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray | None:
    """[Hf, Wf] bool: the cells whose flow validity (rafd.flow_validity) reaches FLOW_VALID_MIN, the only ones
    given an arrow; None when no validity is given (every cell may be drawn)."""
    if validity is None:
        return None
    valid = np.asarray(validity, dtype=np.float64)
    if valid.shape != tuple(shape):
        raise ValueError(f"validity of shape {valid.shape} for a flow grid of {tuple(shape)}")
    return valid >= FLOW_VALID_MIN


# ---------------------------------------------------------------- a model-frame picture (evaluation examples)
def _draw_flow(
    canvas: np.ndarray,
    flow: np.ndarray,
    image_size: int,
    resolution: float,
    step: int,
    scale: float,
    min_flow: float,
    upscale: int,
    keep: np.ndarray | None = None,
) -> None:
    """Arrows for every `step`-th cell of a [2, Hf, Wf] metre flow whose magnitude exceeds `min_flow` (and, with
    `keep` [Hf, Wf], only the cells it marks)."""
    if flow.ndim != 3 or flow.shape[0] != 2 or flow.shape[1] != flow.shape[2]:
        raise ValueError(f"flow must be [2, Hf, Hf] (square feature map), got {flow.shape}")
    centres = feature_cell_centres(flow.shape[1], image_size, resolution)  # [Hf, Wf, 2] metres, now
    vectors = np.moveaxis(flow, 0, -1)  # [Hf, Wf, 2]
    heads = metres_to_pixels(centres, image_size, resolution)[::step, ::step].reshape(-1, 2)  # [P, 2]
    tails = metres_to_pixels(centres - scale * vectors, image_size, resolution)[::step, ::step].reshape(-1, 2)
    moving = np.linalg.norm(vectors[::step, ::step].reshape(-1, 2), axis=-1) > min_flow  # [P]
    if keep is not None:
        moving &= np.asarray(keep, dtype=bool)[::step, ::step].reshape(-1)
    for tail, head in zip(tails[moving] * upscale, heads[moving] * upscale):
        draw_arrow(canvas, tuple(tail), tuple(head), FLOW_COLOUR)


def draw_detections(
    image: np.ndarray,
    gt_boxes: np.ndarray,
    pred_boxes: np.ndarray,
    pred_scores: np.ndarray,
    resolution: float,
    flow: np.ndarray | None = None,
    flow_step: int = 2,
    flow_scale: float = 2.0,
    min_flow: float = 1e-3,
    upscale: int = 1,
    score_threshold: float | None = None,
    all_flow: bool = False,
    validity: np.ndarray | None = None,
) -> np.ndarray:
    """Radar scan uint8 [S, S] (centred on the radar) -> BGR uint8 [S*upscale + legend, S*upscale, 3] with boxes,
    flow, non-overlapping score labels, a distance bar and a legend strip below the scan.

    Boxes are [N, 5] metres; `score_threshold`: the threshold the predictions were chosen by, stated in the legend
    (the caller passes only boxes at or above it). Flow is [2, Hf, Wf] metres in this frame's grid, drawn
    `flow_scale` times longer than the true motion for every `flow_step`-th cell moving more than `min_flow`
    metres, and (unless `all_flow`) only where it means something: cells with returns or near a box
    (meaningful_cells). With `validity` [Hf, Wf] (rafd.flow_validity) only the cells measured over the full search
    range (validity >= FLOW_VALID_MIN) get an arrow, `all_flow` or not.
    """
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or image.shape[0] != image.shape[1]:
        raise ValueError(f"image must be a square uint8 [S, S] (or [S, S, 3]) scan, got {image.dtype} {image.shape}")
    if upscale < 1 or flow_step < 1:
        raise ValueError(f"upscale and flow_step must be >= 1, got {upscale} and {flow_step}")
    size = image.shape[0]
    view = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    if upscale > 1:
        view = cv2.resize(view, (size * upscale, size * upscale), interpolation=cv2.INTER_NEAREST)
    pred_boxes = np.asarray(pred_boxes, dtype=np.float64).reshape(-1, 5)
    pred_scores = np.asarray(pred_scores, dtype=np.float64).reshape(-1)
    if len(pred_boxes) != len(pred_scores):
        raise ValueError(f"{len(pred_boxes)} predicted boxes but {len(pred_scores)} scores")
    gt_boxes = np.asarray(gt_boxes, dtype=np.float64).reshape(-1, 5)
    if flow is not None:
        flow = np.asarray(flow, dtype=np.float64)
        keep = None
        if not all_flow:
            grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
            boxes = np.concatenate([pred_boxes, gt_boxes])[:, :2]
            keep = meaningful_cells(
                grey,
                (flow.shape[1], flow.shape[2]),
                size // flow.shape[1],
                centres=metres_to_pixels(boxes, size, resolution) if len(boxes) else None,
                near_px=NEAR_BOX_M / resolution,
            )
        valid = valid_cells(validity, (flow.shape[1], flow.shape[2]))
        if valid is not None:
            keep = valid if keep is None else keep & valid
        _draw_flow(view, flow, size, resolution, flow_step, flow_scale, min_flow, upscale, keep)
    gt_polygons = box_polygons_pixels(gt_boxes, size, resolution)
    draw_polygons(view, gt_polygons, GT_COLOUR, upscale)
    polygons = box_polygons_pixels(pred_boxes, size, resolution)  # [N, 4, 2]
    draw_polygons(view, polygons, PRED_COLOUR, upscale)
    font_scale = 0.35 if upscale < 3 else 0.45
    draw_scores(view, polygons * upscale, pred_scores, PRED_COLOUR, font_scale)
    draw_scale_bar(view, upscale / resolution, font_scale)
    legend = Legend(
        truth=True,
        flow_px_per_m=flow_scale * upscale / resolution if flow is not None else None,
        flow_scale=flow_scale,
        font_scale=font_scale,
        score_threshold=score_threshold,
        flow_where=_flow_where(all_flow, validity is not None),
    )
    width = view.shape[1]
    strip = np.full((legend_height(legend, width - 8) + 8, width, 3), PANEL_COLOUR, np.uint8)
    draw_legend(strip, (4, 4), width - 8, legend)
    return np.concatenate([view, strip], axis=0)


def _flow_where(all_flow: bool, valid_only: bool) -> str | None:
    """The legend's "at ..." of the flow arrows."""
    if valid_only:
        return "valid cells" if all_flow else "valid cells with returns or boxes"
    return None if all_flow else "returns or boxes"


def plot_precision_recall(curves: dict[float, tuple[np.ndarray, np.ndarray, float]], path: str | Path) -> Path:
    """{IoU threshold: (precision [D], recall [D], AP)} -> a PNG (or any matplotlib format) at `path`."""
    # Object-oriented Agg canvas: no pyplot global state, no backend switch for the caller.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(5, 4), dpi=100)
    FigureCanvasAgg(figure)
    axes = figure.add_subplot(1, 1, 1)
    for threshold, (precision, recall, ap) in sorted(curves.items()):
        axes.plot(np.asarray(recall), np.asarray(precision), label=f"IoU {threshold:g}: AP {ap:.3f}")
    axes.set_xlabel("recall")
    axes.set_ylabel("precision")
    axes.set_xlim(0.0, 1.0)
    axes.set_ylim(0.0, 1.05)
    axes.grid(True, alpha=0.3)
    if curves:
        axes.legend(loc="lower left")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path)
    return path
