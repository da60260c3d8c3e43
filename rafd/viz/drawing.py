"""Drawing primitives for the pictures (opencv): colours, sub-pixel polygons and arrows, score labels that never
overlap (place_labels).

Colours are BGR (opencv order, ready for cv2.imwrite): ground truth green, predictions red with their score, flow
arrows yellow (tail where the content was at t-1, head where it is at t).
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

GT_COLOUR = (0, 255, 0)
PRED_COLOUR = (0, 0, 255)
FLOW_COLOUR = (0, 255, 255)
TRACK_COLOUR = (255, 160, 40)  # velocity arrows and trails (BGR: a light blue)
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
    suffixes: Sequence[str] | None = None,
) -> list[Rect | None]:
    """Score labels for [N, 4, 2] canvas-pixel polygons (each followed by its suffix, e.g. its track), placed best
    score first and never overlapping (a thin leader line joins a label pushed away from its box) -> the label rects
    in the polygons' order."""
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    if len(polygons) == 0:
        return []
    order = [int(k) for k in np.argsort(-scores, kind="stable")]
    texts = [f"{scores[k]:.2f}{'' if suffixes is None else suffixes[k]}" for k in order]
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
