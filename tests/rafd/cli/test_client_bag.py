"""rafd client BAG --bag-out OUT against a real in-process service (the FakeRunner's: its boxes are a function of
the posted scan, so equal answers mean equal scans reached the model): the real Oxford and Boreas-RT scans recorded
as Navtech's driver records them answer as the same scans posted directly, and OUT is read by two readers no one
here wrote: mcap-ros2-support from the schemas embedded in it, rosbags with only the bag's own definitions."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

pytest.importorskip("rosbags", reason="ROS 2 bags need the ros extra")
mcap_ros2 = pytest.importorskip("mcap_ros2.decoder", reason="mcap-ros2-support (dev extra) reads the bags back")

from rafd.cli.client import main  # noqa: E402
from rafd.detect_client import FrameFields, base64_png, detect_request, json_body, png_bytes, post  # noqa: E402
from rafd.ros.axes import box_to_ros, quaternion_yaw  # noqa: E402
from rafd.ros.reader import read_scans, scan_topic  # noqa: E402
from tests.rafd.ros.conftest import native_scans  # noqa: E402
from tests.utils.answers_testing import chain_free  # noqa: E402
from tools.navtech_bag import STAMP_ROW, write_navtech_bag  # noqa: E402


def decode_all(bag: Path) -> dict[str, list[tuple[int, object]]]:
    """{topic: [(log time, message)]} of every message, decoded by mcap-ros2-support from the embedded schemas."""
    from mcap.reader import make_reader

    (mcap,) = bag.glob("*.mcap")
    found: dict[str, list[tuple[int, object]]] = {}
    with mcap.open("rb") as handle:
        reader = make_reader(handle, decoder_factories=[mcap_ros2.DecoderFactory()])
        for _, channel, message, decoded in reader.iter_decoded_messages():
            found.setdefault(channel.topic, []).append((message.log_time, decoded))
    return found


def direct_answers(url: str, scans: list[np.ndarray], stamps_ns: list[int], range_bin_m: float | None) -> list[dict]:
    """The same native scans POSTed directly (their PNGs, the bag's stamps), as a client without a bag would."""
    answers, previous = [], None
    for native, stamp in zip(scans, stamps_ns):
        fields = FrameFields(stamp / 1e9, "direct", None, previous, range_bin_m)
        with post(url, detect_request(json_body(fields, base64_png(png_bytes(native)))), 30.0) as response:
            answers.append(json.loads(response.read()))
        previous = stamp / 1e9
    return answers


def run_through_bag(url: str, tmp_path: Path, scans: list[np.ndarray], range_bin_m: float, name: str) -> tuple:
    bag = write_navtech_bag(tmp_path / f"{name}_in", scans, range_bin_m)
    out, answers_dir = tmp_path / f"{name}_out", tmp_path / f"{name}_answers"
    assert main([str(bag), "--url", url, "--bag-out", str(out), "--out", str(answers_dir), "--quiet"]) == 0
    answers = [json.loads(line) for line in (answers_dir / "answers.jsonl").read_text().splitlines()]
    stamps = [int(np.ascontiguousarray(s[STAMP_ROW, :8]).view("<i8")[0]) * 1000 for s in scans]
    bin_read = next(iter(read_scans(scan_topic(bag))))[1].range_bin_m
    return answers, stamps, out, bin_read


def comparable(answer: dict) -> dict:
    same = {k: answer[k] for k in ("flow", "pose", "frames_used", "input")} | {"t": answer["timestamp"]}
    return same | {"boxes": chain_free(answer["boxes"])}


def assert_bag_holds_the_answers(out: Path, answers: list[dict], stamps: list[int]) -> None:
    """One Detection3DArray and one RadarTracks per scan at its stamp, boxes in REP-103 axes equal (1 mm) to the
    answers', odometry as the answers' poses; every message of every topic decodes."""
    decoded = decode_all(out)
    assert set(decoded) >= {"/rafd/detections", "/rafd/tracks", "/rafd/odometry", "/tf"}
    detections, tracks = decoded["/rafd/detections"], decoded["/rafd/tracks"]
    assert [t for t, _ in detections] == stamps and [t for t, _ in tracks] == stamps
    for answer, (stamp, array), (_, track_array) in zip(answers, detections, tracks):
        assert array.header.stamp.sec * 10**9 + array.header.stamp.nanosec == stamp
        assert array.header.frame_id == "radar" and len(array.detections) == len(answer["boxes"])
        assert len(track_array.tracks) == len(answer["boxes"])
        for box, detection, track in zip(answer["boxes"], array.detections, track_array.tracks):
            expected = box_to_ros(box["x"], box["y"], box["width"], box["length"], box["yaw"])
            centre = detection.bbox.center
            got = (centre.position.x, centre.position.y, detection.bbox.size.x, detection.bbox.size.y)
            assert np.abs(np.subtract(got, (expected.x, expected.y, expected.size_x, expected.size_y))).max() < 1e-3
            o = centre.orientation
            assert abs(math.remainder(quaternion_yaw(o.x, o.y, o.z, o.w) - expected.yaw, 2 * math.pi)) < 1e-3
            assert detection.results[0].hypothesis.class_id == box["class"]
            assert abs(detection.results[0].hypothesis.score - box["score"]) < 1e-9
            assert (track.position.x, track.position.y) == pytest.approx((expected.x, expected.y), abs=1e-3)
            assert detection.id == box["track_id"]
            if box["velocity"] is None:
                assert math.isnan(track.velocity.x) and math.isnan(track.velocity.y)
            else:  # the ground velocity turned into REP-103 axes (x forward = service y, y left = -service x)
                velocity = (track.velocity.x, track.velocity.y)
                assert velocity == pytest.approx((box["velocity"]["y"], -box["velocity"]["x"]), abs=1e-4)
            assert all(math.isnan(v) for v in track.position_covariance)  # the answer gives no position covariance
    uuid_of: dict[str, bytes] = {}  # one UUID per track id, the same in every scan, never shared by two tracks
    for answer, (_, track_array) in zip(answers, tracks):
        for box, track in zip(answer["boxes"], track_array.tracks):
            assert uuid_of.setdefault(box["track_id"], bytes(track.uuid.uuid)) == bytes(track.uuid.uuid)
    assert len(set(uuid_of.values())) == len(uuid_of) and all(len(u) == 16 for u in uuid_of.values())
    for answer, (_, odometry) in zip(answers, decoded["/rafd/odometry"]):
        pose = odometry.pose.pose.position
        assert (pose.x, pose.y) == pytest.approx((answer["pose"]["y"], -answer["pose"]["x"]), abs=1e-9)
        assert odometry.header.frame_id == "odom" and odometry.child_frame_id == "radar"


def read_back_with_its_own_definitions(out: Path) -> int:
    """rosbags reads OUT with only the definitions the bag carries (no default types): messages read."""
    from rosbags.highlevel import AnyReader

    count = 0
    with AnyReader([out]) as reader:
        for connection, _, raw in reader.messages():
            reader.deserialize(raw, connection.msgtype)
            count += 1
    return count


def test_a_synthetic_bag_round_trip_with_scan_and_flow(service_url: str, tmp_path: Path):
    scans = native_scans(3)
    bag = write_navtech_bag(tmp_path / "in", scans, 0.0864)
    out = tmp_path / "out"
    args = [str(bag), "--url", service_url, "--bag-out", str(out), "--bag-scan", "--bag-flow", "--quiet"]
    assert main(args) == 0
    decoded = decode_all(out)
    assert len(decoded["/rafd/scan"]) == 3 and len(decoded["/rafd/flow"]) == 3
    grid = decoded["/rafd/scan"][0][1]
    assert (grid.info.width, grid.info.height) == (1152, 1152) and grid.header.frame_id == "radar"
    assert read_back_with_its_own_definitions(out) == sum(len(v) for v in decoded.values())
    sqlite_out = tmp_path / "out_sqlite"
    assert (
        main([str(bag), "--url", service_url, "--bag-out", str(sqlite_out), "--bag-storage", "sqlite3", "--quiet"]) == 0
    )
    assert read_back_with_its_own_definitions(sqlite_out) == 4 * 3  # detections, tracks, odometry, tf per scan


@pytest.mark.slow
def test_real_oxford_scans_through_a_navtech_bag_answer_as_posted_directly(service_url, tmp_path, oxford_sample):
    paths = sorted((oxford_sample / "radar").glob("*.png"))
    scans = [cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in paths]
    answers, stamps, out, bin_read = run_through_bag(service_url, tmp_path, scans, 0.0432, "oxford")
    assert len(answers) == 13 and bin_read == pytest.approx(0.0432)
    assert all(
        a["input"]["native_format"] == "oxford" and a["input"]["native_range_bin_m"] == bin_read for a in answers
    )
    direct = direct_answers(service_url, scans, stamps, None)  # no field: the width's guess, Oxford's 0.0432
    assert [comparable(a) for a in answers] == [comparable(d) for d in direct]
    assert sum(len(a["boxes"]) for a in answers) > 0
    assert_bag_holds_the_answers(out, answers, stamps)
    assert read_back_with_its_own_definitions(out) == 4 * 13


def test_the_real_boreas_rt_scan_through_a_navtech_bag_answers_as_posted_directly(
    service_url, tmp_path, boreas_rt_scan
):
    native = cv2.imread(str(boreas_rt_scan), cv2.IMREAD_UNCHANGED)
    answers, stamps, out, bin_read = run_through_bag(service_url, tmp_path, [native], 0.04381, "boreas")
    # The driver's message has no chirp column: the bag's scan reads as boreas-2021 with every azimuth measured; the
    # file posted directly reads as boreas-rt, its chirp column not taken for validity: the same scan either way.
    assert answers[0]["input"]["native_range_bin_m"] == bin_read
    (direct,) = direct_answers(service_url, [native], stamps, bin_read)
    assert direct["input"]["native_format"] == "boreas-rt"
    assert comparable(answers[0])["boxes"] == comparable(direct)["boxes"] and answers[0]["boxes"]
    assert_bag_holds_the_answers(out, answers, stamps)


def test_bad_bags_fail_with_a_message_and_leave_no_output(service_url: str, tmp_path: Path, capsys):
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"\x89MCAP0\r\n" + bytes(100))
    out = tmp_path / "never"
    assert main([str(garbage), "--url", service_url, "--bag-out", str(out), "--quiet"]) == 2
    assert "garbage.mcap" in capsys.readouterr().err and not out.exists()
    assert not list(tmp_path.glob(".never*"))
    existing = tmp_path / "existing"
    existing.mkdir()
    bag = write_navtech_bag(tmp_path / "ok", native_scans(2), 0.0432)
    assert main([str(bag), "--url", service_url, "--bag-out", str(existing), "--quiet"]) == 2
    assert "exists" in capsys.readouterr().err


def test_a_run_that_fails_midway_leaves_no_bag(service_url: str, tmp_path: Path, capsys):
    """The second scan's encoder angles are all equal (no sweep of a radar): the first scan is answered and written,
    the second fails naming its topic and message, and OUT is not left half-written."""
    scans = native_scans(3)
    scans[1][:, 8:10] = scans[1][0, 8:10]
    bag = write_navtech_bag(tmp_path / "in", scans, 0.0432)
    out = tmp_path / "out"
    assert main([str(bag), "--url", service_url, "--bag-out", str(out), "--quiet"]) == 1
    assert "topic /radar_data/b_scan_msg, message 1" in capsys.readouterr().err
    assert not out.exists() and not list(tmp_path.glob(".out*"))
    backwards = native_scans(3)
    backwards[2] = backwards[0].copy()  # the third scan repeats the first one's times: not after the second's
    bag = write_navtech_bag(tmp_path / "backwards", backwards, 0.0432)
    assert main([str(bag), "--url", service_url, "--bag-out", str(out), "--quiet"]) == 2
    assert "not after the previous message" in capsys.readouterr().err and not out.exists()
