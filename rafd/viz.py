"""Pictures for inspection: detections and flow over a radar scan (opencv), precision-recall plots (matplotlib).

Colours are BGR (opencv order, ready for cv2.imwrite): ground truth green, predictions red with
their score, flow arrows yellow (tail where the content was at t-1, head where it is at t).
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from rafd.geometry import box_polygons_pixels, feature_cell_centres, metres_to_pixels

GT_COLOUR = (0, 255, 0)
PRED_COLOUR = (0, 0, 255)
FLOW_COLOUR = (0, 255, 255)
_SHIFT = 4  # fractional bits for opencv's sub-pixel drawing


def _to_cv_points(uv: np.ndarray, upscale: int) -> np.ndarray:
    """[..., 2] continuous pixels (pixel i covers [i, i+1)) -> int32 fixed-point points for opencv (shift=_SHIFT)."""
    # opencv's integer coordinate i is the centre of pixel i, i.e. continuous i + 0.5.
    return np.round((np.asarray(uv) * upscale - 0.5) * (1 << _SHIFT)).astype(np.int32)


def _draw_boxes(canvas: np.ndarray, polygons: np.ndarray, colour: tuple[int, int, int], upscale: int) -> None:
    """Outline [N, 4, 2] pixel polygons in place."""
    if len(polygons):
        cv2.polylines(canvas, list(_to_cv_points(polygons, upscale)), True, colour, 1, cv2.LINE_8, _SHIFT)


def _draw_flow(
    canvas: np.ndarray, flow: np.ndarray, image_size: int, resolution: float, step: int, scale: float,
    min_flow: float, upscale: int,
) -> None:
    """Arrows for every `step`-th cell of a [2, Hf, Wf] metre flow whose magnitude exceeds `min_flow`."""
    if flow.ndim != 3 or flow.shape[0] != 2 or flow.shape[1] != flow.shape[2]:
        raise ValueError(f"flow must be [2, Hf, Hf] (square feature map), got {flow.shape}")
    centres = feature_cell_centres(flow.shape[1], image_size, resolution)  # [Hf, Wf, 2] metres, now
    vectors = np.moveaxis(flow, 0, -1)  # [Hf, Wf, 2]
    heads = metres_to_pixels(centres, image_size, resolution)[::step, ::step].reshape(-1, 2)  # [P, 2]
    tails = metres_to_pixels(centres - scale * vectors, image_size, resolution)[::step, ::step].reshape(-1, 2)
    moving = np.linalg.norm(vectors[::step, ::step].reshape(-1, 2), axis=-1) > min_flow  # [P]
    for tail, head in zip(_to_cv_points(tails[moving], upscale), _to_cv_points(heads[moving], upscale)):
        cv2.arrowedLine(canvas, tuple(int(t) for t in tail), tuple(int(h) for h in head), FLOW_COLOUR, 1,
                        cv2.LINE_8, _SHIFT, 0.3)


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
) -> np.ndarray:
    """Radar scan uint8 [S, S] (centred on the radar) -> BGR uint8 [S*upscale, S*upscale, 3] with boxes and flow.

    Boxes are [N, 5] metres; flow is [2, Hf, Wf] metres in this frame's grid, drawn `flow_scale` times
    longer than the true motion for every `flow_step`-th cell moving more than `min_flow` metres.
    """
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or image.shape[0] != image.shape[1]:
        raise ValueError(f"image must be a square uint8 [S, S] (or [S, S, 3]) scan, got {image.dtype} {image.shape}")
    if upscale < 1 or flow_step < 1:
        raise ValueError(f"upscale and flow_step must be >= 1, got {upscale} and {flow_step}")
    size = image.shape[0]
    canvas = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    if upscale > 1:
        canvas = cv2.resize(canvas, (size * upscale, size * upscale), interpolation=cv2.INTER_NEAREST)
    pred_boxes = np.asarray(pred_boxes, dtype=np.float64).reshape(-1, 5)
    pred_scores = np.asarray(pred_scores, dtype=np.float64).reshape(-1)
    if len(pred_boxes) != len(pred_scores):
        raise ValueError(f"{len(pred_boxes)} predicted boxes but {len(pred_scores)} scores")
    if flow is not None:
        _draw_flow(canvas, np.asarray(flow, dtype=np.float64), size, resolution, flow_step, flow_scale, min_flow,
                   upscale)
    _draw_boxes(canvas, box_polygons_pixels(np.asarray(gt_boxes, dtype=np.float64).reshape(-1, 5), size, resolution),
                GT_COLOUR, upscale)
    polygons = box_polygons_pixels(pred_boxes, size, resolution)  # [N, 4, 2]
    _draw_boxes(canvas, polygons, PRED_COLOUR, upscale)
    for polygon, score in zip(polygons, pred_scores):
        top = polygon[np.argmin(polygon[:, 1])] * upscale  # label above the box's highest corner
        cv2.putText(canvas, f"{score:.2f}", (int(top[0]), int(top[1]) - 2), cv2.FONT_HERSHEY_SIMPLEX,
                    0.3 * upscale, PRED_COLOUR, 1, cv2.LINE_AA)
    return canvas


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
