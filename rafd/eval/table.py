"""rafd eval's console table: one row per sequence and overall, per recording condition, the figures by range, and
the flow by ring from the crop's edge (format_flow_table, rafd.eval.flow_split).

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
        far = overall.get("far_score_threshold")
        beyond = f" ({far['threshold']:.4g} from {far['from_m']:g} m)" if far else ""
        lines.append(f"\nat the operating threshold {overall['score_threshold']:.4g}{beyond}, by range from the radar:")
        lines.append(f"{'range (m)':<28}{'vehicles':>15}{'recall':>15}{'fp_per_frame':>15}")
        for band in bands:
            recall = f"{band['recall']:.1f}" if band["vehicles"] else "no objects"
            lines.append(
                f"{band['from_m']:>5.0f} - {band['to_m']:<20.0f}{band['vehicles']:>15}{recall:>15}"
                f"{band['fp_per_frame']:>15.3f}"
            )
    return "\n".join(lines)


RING_WIDTH = 9


def _figure(value: Any, digits: int = 4) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    if math.isinf(value):
        return "inf"
    return f"{value:.{digits}f}"


def _rings_text(rings: list[int]) -> str:
    return f"rings {rings[0]}-{rings[-1]}" if rings else "no ring"


def format_flow_table(flow: dict[str, Any]) -> str:
    """report["flow"] as text: EPE on vehicle and background cells, background EPE by ring from the crop's edge and
    the edge ratio, all cells and valid cells only; then the label-free mean |flow| by ring. "-": no cell."""
    if not flow.get("pairs"):
        return "flow by ring: no flow (a one-frame model, or no pair of frames)"
    names = flow["rings"]
    head = ["vehicle", "all rings", *(f"ring {n}" for n in names[:-1]), names[-1], "edge ratio"]
    widths = [10, 11, *([RING_WIDTH] * len(names)), 12]
    label = 34
    if flow["mode"] == "crop":
        where = "detection-grid cells from the crop's edge"
    else:
        where = "detection-grid cells from each tile's own edge (the model sees every tile as a crop)"
    pairs = f"{flow['pairs']} pair{'s' if flow['pairs'] != 1 else ''}"
    lines = [
        f"\nflow of the newest pair (m per frame, ego motion removed), {pairs}; ring k: {where}; "
        f"valid: flow validity >= {flow['flow_valid_min']:g}",
        f"{'':<{label}}" + "".join(f"{h:>{w}}" for h, w in zip(head, widths)),
    ]

    def row(name: str, vehicle: Any, overall: Any, by_ring: list[Any], ratio: Any) -> str:
        cells = [_figure(vehicle), _figure(overall), *(_figure(v) for v in by_ring), _figure(ratio, 2)]
        return f"{name:<{label}}" + "".join(f"{c:>{w}}" for c, w in zip(cells, widths))

    if flow.get("labelled_pairs"):
        lines.append(
            row(
                "EPE (background by ring)",
                flow["vehicle_epe"],
                flow["background_epe"],
                flow["background_epe_by_ring"],
                flow["edge_ratio"],
            )
        )
        lines.append(
            row(
                "EPE, valid cells",
                flow["vehicle_epe_valid"],
                flow["background_epe_valid"],
                flow["background_epe_by_ring_valid"],
                flow["edge_ratio_valid"],
            )
        )
    free = flow["label_free"]
    lines.append(
        row("|flow|, all cells (no labels)", None, free["magnitude"], free["magnitude_by_ring"], free["edge_ratio"])
    )
    lines.append(
        row(
            "|flow|, valid cells (no labels)",
            None,
            free["magnitude_valid"],
            free["magnitude_by_ring_valid"],
            free["edge_ratio_valid"],
        )
    )
    lines.append(
        f"edge ratio: {_rings_text(flow['edge_rings'])} / {names[-1]}; valid rows: "
        f"{_rings_text(flow['edge_rings_valid'])} / {names[-1]} (the outermost rings holding valid cells); "
        "-: no cell, inf: 0 in the interior"
    )
    if not flow.get("labelled_pairs"):
        lines.append("no flow targets (whole scans, or no pair with targets): the label-free rows only")
    if flow.get("repeated_pairs"):
        lines.append(
            f"{flow['repeated_pairs']} of the pairs pair a frame with itself (warm-up padding or --past-as-newest): "
            "their true flow is 0 in every cell"
        )
    return "\n".join(lines)
