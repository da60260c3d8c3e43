"""rafd eval --tracking's console tables: tracks (TrackEval's figures) and velocities, overall, by range and by
weather; the velocity candidates and baselines side by side; the operating point with and without tracks."""

from __future__ import annotations

import math
from typing import Any

TRACK_COLUMNS = ("HOTA", "DetA", "AssA", "HOTA@2m", "MOTA", "IDF1", "IDSW", "objects")
VELOCITY_COLUMNS = (
    "mean",
    "p90",
    "coverage",
    "mean_all",
    "p90_all",
    "mean_moving",
    "p90_moving",
    "mean_parked",
    "moving",
    "matched",
)


def _text(value: Any) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:.2f}" if isinstance(value, float) else str(value)


def _table(title: str, columns: tuple[str, ...], rows: list[tuple[str, dict[str, Any]]]) -> list[str]:
    width = max([24, len(title) + 2, *(len(name) + 2 for name, _ in rows)])
    widths = [max([len(column), 7, *(len(_text(row.get(column))) for _, row in rows)]) + 2 for column in columns]
    lines = [f"{title:<{width}}" + "".join(f"{c:>{w}}" for c, w in zip(columns, widths))]
    for name, row in rows:
        lines.append(f"{name:<{width}}" + "".join(f"{_text(row.get(c)):>{w}}" for c, w in zip(columns, widths)))
    return lines


def _difference(figures: dict[str, Any] | None) -> str:
    """A recall difference in points with its 95% interval, e.g. '+2.6 [-0.4, +5.1]'."""
    if not figures:
        return "-"
    low, high = figures["interval95"]
    return f"{figures['points']:+.1f} [{low:+.1f}, {high:+.1f}]"


def format_tracking(report: dict[str, Any]) -> str:
    """The tracking report of rafd.eval.tracking.evaluate_tracking as plain text."""
    kept = report["identity_kept"]
    threshold = report["score_threshold"]  # a number, or a description when it differs by range
    threshold_text = threshold if isinstance(threshold, str) else f"{threshold:.4f}"
    lines = [
        f"tracking ({report['frames']} scans in {report['sequences']} streams, velocity {report['settings']}, "
        f"score threshold {threshold_text}; TrackEval, 2 m centre matching; HOTA/DetA/AssA "
        "averaged over 0.2-3.8 m, HOTA@2m at 2 m)",
    ]
    rows = [("overall", report["tracking"])]
    rows += [(f"range {band}", figures["tracking"]) for band, figures in report["by_range"].items()]
    rows += [(f"weather {name}", figures["tracking"]) for name, figures in report["by_condition"].items()]
    lines += _table("tracks", TRACK_COLUMNS, rows)
    lines.append(
        f"a matched vehicle keeps its track id from one scan to the next: {_text(kept['percent'])}% "
        f"({kept['kept']} of {kept['pairs']})"
    )
    lines.append("")
    lines.append(
        f"velocity error, m/s (true velocities: {report['velocity_truth'] or 'unknown'}; mean/p90 over matched boxes "
        "with a velocity source, *_all over every matched box, a box without one answering 0 m/s; *_moving and "
        "*_parked: every matched box of a vehicle moving at >= 0.5 m/s, or not)"
    )
    rows = [("overall", report["velocity"])]
    rows += [(f"range {band}", figures["velocity"]) for band, figures in report["by_range"].items()]
    rows += [(f"weather {name}", figures["velocity"]) for name, figures in report["by_condition"].items()]
    lines += _table("velocity", VELOCITY_COLUMNS, rows)
    lines.append("")
    rows = [(f"candidate {mode}", figures["velocity"]) for mode, figures in report["candidates"].items()]
    rows += [(f"baseline {name}", figures) for name, figures in report["baselines"].items()]
    lines += _table("velocity candidates", VELOCITY_COLUMNS, rows)
    tracks = [
        (f"candidate {mode}", figures["tracking"] | {"id_kept": figures["identity_kept"]["percent"]})
        for mode, figures in report["candidates"].items()
    ]
    lines += _table("tracks by candidate", TRACK_COLUMNS + ("id_kept",), tracks)
    study = report.get("time_helps_detection")
    if study:
        lines.append("")
        lines.append(
            f"does time help detection: recall (%) at <= {study['budget_fp_per_frame']:g} false positive per scan, "
            f"each at its best input threshold ({study['vehicles']} vehicles in {study['frames']} scans)"
        )
        rows = []
        for name, figures in study.items():
            if isinstance(figures, dict):
                best, operating = figures["at_budget"], figures["at_operating_threshold"]
                rows.append(
                    (
                        name,
                        {
                            "recall": best["recall"],
                            "fp/scan": best["fp_per_frame"],
                            "threshold": best["threshold"],
                            "recall@op": operating.get("recall"),
                            "fp/scan@op": operating.get("fp_per_frame"),
                            "vs detections": _difference(figures.get("difference_from_detections")),
                        },
                    )
                )
        columns = ("recall", "fp/scan", "threshold", "recall@op", "fp/scan@op", "vs detections")
        lines += _table("answer", columns, rows)
    return "\n".join(lines)
