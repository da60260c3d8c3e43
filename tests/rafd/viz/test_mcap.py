"""rafd.viz.mcap: frames, orientation and flow arrows in Foxglove's conventions, read back with the mcap reader."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

pytest.importorskip("foxglove", reason="MCAP logs need the logs extra (foxglove-sdk)")
from mcap.reader import make_reader  # noqa: E402
from mcap_protobuf.decoder import DecoderFactory  # noqa: E402

from rafd.viz.mcap import LoggedFrame, RadarMcapLog  # noqa: E402


def frame(timestamp_ns: int, flow: bool) -> LoggedFrame:
    scan = np.zeros((16, 16), np.uint8)
    scan[2, 3] = 200  # top row area: forward of the radar, left of centre
    return LoggedFrame(
        timestamp_ns=timestamp_ns,
        scan_png=cv2.imencode(".png", scan)[1].tobytes(),
        scan_size=16,
        resolution=0.5,
        crop=(4, 8),
        crop_pixels=scan[4:12, 4:12],
        pose=np.array([10.0, -2.0, math.pi / 2]),
        boxes=np.array([[1.0, 2.0, 1.5, 4.0, 0.5]]),
        scores=np.array([0.9]),
        classes=["vehicle"],
        polygons=np.array([[[1.0, 1.0], [3.0, 1.0], [3.0, 5.0], [1.0, 5.0]]]),
        flow_heads=np.array([[5.0, 5.0], [0.0, 3.0]]) if flow else None,
        flow_motions=np.array([[1.0, 0.0], [0.0, 2.0]]) if flow else None,
    )


def decoded(path: Path, topic: str) -> list:
    with path.open("rb") as handle:
        return [
            (m.log_time, p)
            for _, _, m, p in make_reader(handle, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                topics=[topic]
            )
        ]


def test_boxes_poses_grid_and_arrows_follow_foxgloves_conventions(tmp_path: Path):
    path = tmp_path / "log.mcap"
    with RadarMcapLog(path) as log:
        log.write(frame(1_574_859_771_744_660_272, flow=False))
        log.write(frame(1_574_859_771_977_525_228, flow=True))
    (t0, update), (t1, _) = decoded(path, "/radar/detections")
    assert (t0, t1) == (1_574_859_771_744_660_272, 1_574_859_771_977_525_228)  # nanosecond-exact log times
    entity = update.entities[0]
    assert (entity.timestamp.seconds, entity.timestamp.nanos) == (1_574_859_771, 744_660_272)
    cube = entity.cubes[0]
    assert 2 * math.atan2(cube.pose.orientation.z, cube.pose.orientation.w) == pytest.approx(0.5)  # CCW about +z
    _, transform = decoded(path, "/tf")[0]
    assert 2 * math.atan2(transform.rotation.z, transform.rotation.w) == pytest.approx(math.pi / 2)
    _, grid = decoded(path, "/radar/scan/grid")[0]
    # The crop's top-left pixel (4, 4) of a 16 px scan at 0.5 m: x = -2 m; its bottom row v = 12: y = -2 m.
    assert (grid.pose.position.x, grid.pose.position.y) == (-2.0, -2.0) and grid.cell_size.x == 0.5
    flows = decoded(path, "/radar/flow")
    assert len(flows) == 1 and flows[0][0] == 1_574_859_771_977_525_228  # only the frame that has flow
    right, forward = flows[0][1].entities[0].arrows
    assert (right.pose.position.x, right.pose.position.y) == (4.0, 5.0)  # tail = head - motion
    assert 2 * math.atan2(right.pose.orientation.z, right.pose.orientation.w) == pytest.approx(0.0)
    assert (forward.pose.position.x, forward.pose.position.y) == (0.0, 1.0)
    assert 2 * math.atan2(forward.pose.orientation.z, forward.pose.orientation.w) == pytest.approx(math.pi / 2)
    assert forward.shaft_length + forward.head_length == pytest.approx(2.0)
    with pytest.raises(RuntimeError, match="closed"):
        log.write(frame(1_574_859_772_000_000_000, flow=False))


def test_a_log_in_a_missing_folder_is_refused(tmp_path: Path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        RadarMcapLog(tmp_path / "missing" / "log.mcap")


def test_logged_answers_carry_flow_arrows_only_for_valid_cells():
    from rafd.viz.mcap import frame_from_answer

    values = np.zeros((2, 4, 4))
    values[0] = 1.0  # every cell moves 1 m right
    answer = {
        "pose": {"x": 0.0, "y": 0.0, "yaw": 0.0},
        "boxes": [],
        "input": {
            "posted_size": 16,
            "model_size": 16,
            "covered": {"side_px": 16, "offset_px": 0, "side_m": 8.0, "range_m": None, "tiles": 1},
        },
        "flow": {
            "shape": [2, 4, 4],
            "encoding": "list",
            "values": values.tolist(),
            "grid": {"height": 4, "width": 4, "cell_size_m": 2.0, "stride_px": 4, "origin_px": [0, 0]},
        },
    }
    scan = np.zeros((16, 16), np.uint8)
    args = (answer, cv2.imencode(".png", scan)[1].tobytes(), 16, 0.5, scan, 0)
    every = frame_from_answer(*args)
    validity = np.zeros((4, 4))
    validity[1:3, 1:3] = 1.0
    valid = frame_from_answer(*args, validity=validity)
    assert len(every.flow_heads) == 16 and len(valid.flow_heads) == 4
    np.testing.assert_allclose(np.abs(valid.flow_heads), 1.0)  # the four centre cells, 1 m from the radar
