"""rafd eval's console table: one row per sequence and overall, per recording condition, and the figures by range.

Headers are printed whole (each column as wide as its header); a figure that is not defined says why instead of
printing nan: "no objects" (no labelled vehicle in those frames: AP and recall have nothing to find), "no flow"
(no cell with a flow target: a one-frame model, or no pair of frames), "no frames".
"""

from __future__ import annotations

import math
from typing import Any

TABLE_COLUMNS = (
    "mAP@0.3",
    "mAP@0.5",
    "mAP@0.7",
    "centre_AP",
    "recall_at_1fp",
    "recall_at_threshold",
    "fp_per_frame_at_threshold",
    "epe_all",
    "frames",
)


NEEDS_OBJECTS = ("mAP@", "centre_AP", "recall_")  # columns with no meaning on frames without any vehicle
MIN_WIDTH = 11  # "no objects" and a figure like 100.0000 fit


def cell(column: str, row: dict[str, Any]) -> str:
    """One figure as text, or why it is not defined."""
    value = row.get(column)
    if column != "frames" and not row.get("frames"):
        return "no frames"
    undefined = value is None or (isinstance(value, float) and not math.isfinite(value))
    if column.startswith(NEEDS_OBJECTS) and row.get("objects") == 0:
        return "no objects"
    if not undefined:
        return f"{value:.4f}" if isinstance(value, float) else str(value)
    if column.startswith("epe"):
        return "no flow"
    return "-" if value is None else "undefined"


def _rows(title: str, rows: list[tuple[str, dict[str, Any]]]) -> list[str]:
    width = max([28, len(title) + 2, *(len(name) + 2 for name, _ in rows)])
    widths = [max(len(column), MIN_WIDTH) + 2 for column in TABLE_COLUMNS]
    lines = [f"{title:<{width}}" + "".join(f"{c:>{w}}" for c, w in zip(TABLE_COLUMNS, widths))]
    for name, row in rows:
        lines.append(f"{name:<{width}}" + "".join(f"{cell(c, row):>{w}}" for c, w in zip(TABLE_COLUMNS, widths)))
    return lines


def format_table(
    overall: dict[str, Any],
    per_sequence: dict[str, dict[str, Any]],
    per_condition: dict[str, dict[str, Any]] | None = None,
) -> str:
    """Plain-text table: one row per sequence plus the overall row; then, where the sequences' meta.json name
    their recording condition, one row per condition; then the figures by range."""
    lines = _rows("sequence", [*per_sequence.items(), ("OVERALL", overall)])
    every = [overall, *per_sequence.values(), *(per_condition or {}).values()]
    if any(cell(c, r) == "no objects" for r in every for c in TABLE_COLUMNS):
        lines.append("no objects: those frames hold no labelled vehicle, so AP and recall are not defined")
    if per_condition:
        lines += ["", *_rows("condition", list(per_condition.items()))]
    bands = [b for b in overall.get("by_range_at_threshold", []) if b["vehicles"] or b["fp_per_frame"]]
    if bands:
        lines.append(f"\nat the operating threshold {overall['score_threshold']:.4g}, by range from the radar:")
        lines.append(f"{'range (m)':<28}{'vehicles':>15}{'recall':>15}{'fp_per_frame':>15}")
        for band in bands:
            recall = f"{band['recall']:.1f}" if band["vehicles"] else "no objects"
            lines.append(
                f"{band['from_m']:>5.0f} - {band['to_m']:<20.0f}{band['vehicles']:>15}{recall:>15}"
                f"{band['fp_per_frame']:>15.3f}"
            )
    return "\n".join(lines)
