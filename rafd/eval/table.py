"""rafd-eval's console table: one row per sequence and overall, per recording condition, and the figures by range."""

from __future__ import annotations

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


def _rows(title: str, rows: list[tuple[str, dict[str, Any]]]) -> list[str]:
    lines = [f"{title:<28}" + "".join(f"{c[:14]:>15}" for c in TABLE_COLUMNS)]
    for name, row in rows:
        cells = []
        for column in TABLE_COLUMNS:
            value = row.get(column)
            cells.append(f"{value:>15.4f}" if isinstance(value, float) else f"{str(value):>15}")
        lines.append(f"{name:<28}" + "".join(cells))
    return lines


def format_table(
    overall: dict[str, Any],
    per_sequence: dict[str, dict[str, Any]],
    per_condition: dict[str, dict[str, Any]] | None = None,
) -> str:
    """Plain-text table: one row per sequence plus the overall row; then, where the sequences' meta.json name
    their recording condition, one row per condition; then the figures by range."""
    lines = _rows("sequence", [*per_sequence.items(), ("OVERALL", overall)])
    if per_condition:
        lines += ["", *_rows("condition", list(per_condition.items()))]
    bands = [b for b in overall.get("by_range_at_threshold", []) if b["vehicles"] or b["fp_per_frame"]]
    if bands:
        lines.append(f"\nat the operating threshold {overall['score_threshold']:.4g}, by range from the radar:")
        lines.append(f"{'range (m)':<28}{'vehicles':>15}{'recall':>15}{'fp_per_frame':>15}")
        for band in bands:
            lines.append(
                f"{band['from_m']:>5.0f} - {band['to_m']:<20.0f}{band['vehicles']:>15}{band['recall']:>15.1f}"
                f"{band['fp_per_frame']:>15.3f}"
            )
    return "\n".join(lines)
