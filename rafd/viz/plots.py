"""Evaluation pictures: detections and flow over a radar scan in the model frame (opencv), precision-recall plots
(matplotlib). The primitives are rafd.viz.drawing, the legend and scale bar rafd.viz.legend, the choice of flow
cells rafd.viz.flow_cells; the service answer's picture (model crop zoomed, side panel) is rafd.viz.answer.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from rafd.geometry import box_polygons_pixels, feature_cell_centres, metres_to_pixels
from rafd.viz.drawing import FLOW_COLOUR, GT_COLOUR, PANEL_COLOUR, PRED_COLOUR, draw_arrow, draw_polygons, draw_scores
from rafd.viz.flow_cells import NEAR_BOX_M, meaningful_cells, valid_cells
from rafd.viz.legend import Legend, draw_legend, draw_scale_bar, legend_height


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
