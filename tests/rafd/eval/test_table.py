"""rafd eval's console table: whole headers, and a reason instead of nan where a figure is not defined."""

from __future__ import annotations

import math

from rafd.eval.table import TABLE_COLUMNS, format_flow_table, format_table

NAN = math.nan


def row(**figures):
    base = {"frames": 5, "objects": 3, "mAP@0.3": 50.0, "mAP@0.5": 40.0, "mAP@0.7": 10.0, "centre_AP": 60.0}
    base |= {"recall_at_1fp": 33.3, "recall_at_threshold": 66.7, "fp_per_frame_at_threshold": 0.2, "epe_all": 0.12}
    return base | figures


def test_headers_are_printed_whole():
    header = format_table(row(), {"sim_1": row()}).splitlines()[0]
    for column in TABLE_COLUMNS:
        assert f" {column}" in header, column  # not cut (recall_at_thre, fp_per_frame_a)


def test_undefined_figures_say_why_instead_of_nan():
    empty = row(objects=0, recall_at_1fp=NAN, recall_at_threshold=NAN, epe_all=NAN, **{"mAP@0.3": 0.0})
    text = format_table(empty, {"tiny_foggy": empty, "sim_1": row()})
    assert "nan" not in text
    lines = text.splitlines()
    foggy = next(line for line in lines if line.startswith("tiny_foggy"))
    assert foggy.split().count("no") == 7  # six "no objects" (mAP x3, centre AP, recalls x2) and one "no flow"
    assert "no flow" in foggy and "0.2000" in foggy
    assert any(line.startswith("no objects: ") for line in lines)  # and the table says what that means
    sim = next(line for line in lines if line.startswith("sim_1"))
    assert "50.0000" in sim and "no " not in sim
    assert "no frames" in format_table({"frames": 0}, {})


def test_the_flow_table_prints_vehicle_background_and_rings_with_a_dash_where_no_cell_is():
    import numpy as np

    from rafd.eval.flow_split import flow_report, ring_map, tally_pair

    flow = np.zeros((2, 32, 32))
    flow[0][ring_map(32, 32) == 0] = 1.0
    validity = np.ones((32, 32))
    validity[ring_map(32, 32) == 0] = 0.0
    report = flow_report(tally_pair(flow, validity, np.zeros_like(flow), np.ones((32, 32)), np.zeros((32, 32))))
    lines = format_flow_table(report).splitlines()
    header = next(line for line in lines if "ring 0" in line)
    for column in ("vehicle", "all rings", "ring 7", "8+", "edge ratio"):
        assert column in header
    background = next(line for line in lines if line.startswith("EPE (background by ring)"))
    assert background.split()[-10:] == ["1.0000"] + ["0.0000"] * 8 + ["inf"]  # ring 0 .. 8+, edge ratio
    valid = next(line for line in lines if line.startswith("EPE, valid cells"))
    assert valid.split()[5] == "-"  # ring 0 holds no valid cell
    assert "rings 1-2 / 8+" in lines[-1] and "nan" not in "\n".join(lines)
