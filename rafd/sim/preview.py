"""Side-by-side picture: a simulated scan (its boxes drawn) and a real RADIATE scan (image only), same crop and scale.

The real sample's labels are a frozen test set: the preview shows its scan, never its boxes."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from rafd.geometry import RADIATE_SCAN_SIZE, box_to_radiate, centre_crop, radiate_polygon
from rafd.sim.sensor import Difficulty
from rafd.sim.sequence import run_simulation

BOX_COLOUR = (0, 0, 255)  # BGR red


def draw_boxes(image: np.ndarray, polygons: list[np.ndarray], crop: int) -> np.ndarray:
    """uint8 [S, S] full scan + [4, 2] full-scan pixel polygons -> BGR [crop, crop] centre crop with outlines."""
    shift = (image.shape[0] - crop) / 2.0
    canvas = cv2.cvtColor(centre_crop(image, crop), cv2.COLOR_GRAY2BGR)
    for polygon in polygons:
        points = np.round((np.asarray(polygon) - shift) * 4).astype(np.int32)  # 2 fractional bits
        cv2.polylines(canvas, [points], True, BOX_COLOUR, 1, cv2.LINE_AA, shift=2)
    return canvas


def real_panel(sample_dir: Path, frame: int, crop: int) -> np.ndarray:
    """A real RADIATE frame (1-based number), centre-cropped, without its labels."""
    path = sample_dir / "Navtech_Cartesian" / f"{frame:06d}.png"
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FileNotFoundError(f"cannot read the real scan {path}")
    return draw_boxes(image, [], crop)


def simulated_panel(seed: int, frame: int, crop: int, difficulty: Difficulty) -> np.ndarray:
    """A simulated full-size frame (1-based) with its annotations drawn through the RADIATE polygon path."""
    sequence = run_simulation(seed, frame, "preview", RADIATE_SCAN_SIZE, difficulty, name="preview")
    polygons = []
    for obj in sequence.objects:
        box = obj.boxes[frame - 1]
        if np.isfinite(box[0]):
            polygons.append(radiate_polygon(*box_to_radiate(box, RADIATE_SCAN_SIZE, sequence.resolution)))
    return draw_boxes(sequence.images[frame - 1], polygons, crop)


def render_preview(
    out_path: Path,
    sample_dir: Path,
    seed: int = 0,
    frame: int = 4,
    crop: int = 768,
    difficulty: Difficulty = Difficulty(),
) -> Path:
    """Write [crop, 2 * crop + 8] BGR PNG: simulated (left) | real (right), labelled."""
    panels = [simulated_panel(seed, frame, crop, difficulty), real_panel(Path(sample_dir), 1, crop)]
    for panel, label in zip(panels, ("simulated", f"real: {Path(sample_dir).name}")):
        cv2.putText(panel, label, (10, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 1, cv2.LINE_AA)
    gap = np.full((crop, 8, 3), 255, np.uint8)
    picture = np.concatenate([panels[0], gap, panels[1]], 1)
    out_path = Path(out_path)
    if not cv2.imwrite(str(out_path), picture):
        raise OSError(f"could not write the preview {out_path}")
    return out_path
