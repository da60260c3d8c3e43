"""rafd.data.read_sequence on the real tiny_foggy sample and on simulated folders, including bad data."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest

from rafd.data import read_sequence
from rafd.data.folders import list_frames
from rafd.geometry import box_corners, metres_to_pixels
from rafd.scans.cartesian import load_image

RES = 0.173611


def _sdk_polygon(position: list[float], rotation_deg: float) -> np.ndarray:
    """RADIATE SDK construction written out independently: corners of the unrotated (x, y, w, h) box
    rotated about its centre by R(deg2rad(-rotation)) applied to pixel coordinates."""
    x, y, w, h = position
    cx, cy = x + w / 2.0, y + h / 2.0
    theta = math.radians(-rotation_deg)
    out = []
    for px, py in ((x, y), (x + w, y), (x + w, y + h), (x, y + h)):
        dx, dy = px - cx, py - cy
        out.append((cx + math.cos(theta) * dx - math.sin(theta) * dy, cy + math.sin(theta) * dx + math.cos(theta) * dy))
    return np.array(out)


@pytest.fixture(scope="module")
def foggy(radiate_sample: Path):
    return read_sequence(radiate_sample)


def test_tiny_foggy_frames_timestamps_and_split(foggy, radiate_sample: Path) -> None:
    lines = (radiate_sample / "Navtech_Cartesian.txt").read_text().split("\n")
    expected = [(int(line.split()[1]), float(line.split()[3])) for line in lines if line.strip()]
    assert len(foggy.frames) == 18 and len(expected) == 18
    assert [(f.number, f.timestamp) for f in foggy.frames] == expected
    assert [f.number for f in foggy.frames] == list(range(1, 19))
    assert foggy.split == "test" and foggy.name == "fog_6_0" and foggy.image_size == 1152
    assert foggy.condition == "fog"  # RADIATE's meta.json "type"
    assert all(f.image_path == radiate_sample / "Navtech_Cartesian" / f"{f.number:06d}.png" for f in foggy.frames)
    assert foggy.frames[0].load().shape == (1152, 1152) and foggy.load_image(17).dtype == np.uint8


def test_tiny_foggy_every_polygon_equals_the_sdk_construction(foggy, radiate_sample: Path) -> None:
    entries = json.loads((radiate_sample / "annotations" / "annotations.json").read_text())
    checked = 0
    for frame in foggy.frames:
        expected = {}
        for entry in entries:
            annotation = entry["bboxes"][frame.number - 1] if frame.number <= len(entry["bboxes"]) else []
            if annotation:
                expected[entry["id"]] = (entry["class_name"], annotation)
        assert sorted(o.id for o in frame.objects) == sorted(expected)
        for obj in frame.objects:
            class_name, annotation = expected[obj.id]
            assert obj.class_name == class_name
            np.testing.assert_allclose(
                obj.polygon, _sdk_polygon(annotation["position"], annotation["rotation"]), rtol=0, atol=1e-6
            )
            # The metre box reproduces the same corners (the mapping in docs/data.md, "Box convention").
            x0, y0, w, h = annotation["position"]
            np.testing.assert_allclose(
                obj.box,
                [
                    (x0 + w / 2 - 576) * RES,
                    (576 - (y0 + h / 2)) * RES,
                    w * RES,
                    h * RES,
                    math.radians(annotation["rotation"]),
                ],
                atol=1e-9,
            )
            np.testing.assert_allclose(metres_to_pixels(box_corners(obj.box[None])[0], 1152), obj.polygon, atol=1e-6)
            checked += 1
    assert checked == sum(len(f.objects) for f in foggy.frames) > 30  # 44 annotated objects over the 18 frames


def test_tiny_foggy_poses_come_from_odometry_and_are_plausible(foggy) -> None:
    assert foggy.pose_source == "odometry"
    assert foggy.poses.shape == (18, 3)
    np.testing.assert_array_equal(foggy.poses[0], 0.0)
    steps = np.diff(foggy.poses[:, :2], axis=0)
    speeds = np.hypot(*steps.T) / np.diff([f.timestamp for f in foggy.frames])
    assert np.all((speeds > 3.0) & (speeds < 25.0))  # a car in town traffic, not identity, not nonsense
    assert np.all(np.abs(np.diff(foggy.poses[:, 2])) < np.radians(5.0))


def test_odometry_fallback_is_logged_and_can_be_switched_off(sim_copy: Path, caplog: pytest.LogCaptureFixture) -> None:
    (sim_copy / "ego_poses.csv").unlink()
    with caplog.at_level(logging.INFO, logger="rafd.data.reader"):
        sequence = read_sequence(sim_copy)
    assert sequence.pose_source == "odometry" and sequence.poses.shape == (10, 3)
    assert "radar odometry" in caplog.text
    bare = read_sequence(sim_copy, estimate_poses=False)
    assert bare.poses is None and bare.pose_source is None


def test_small_simulated_scan_reads_back_with_its_own_image_size(sim_truth_and_folder) -> None:
    truth, folder = sim_truth_and_folder
    sequence = read_sequence(folder)
    assert sequence.image_size == 384 and sequence.pose_source == "file" and sequence.split == "train_good_weather"
    np.testing.assert_allclose(sequence.poses, truth.poses, atol=1e-12)
    assert sequence.poses_by_frame()[3] is not None and np.allclose(sequence.pose_of(3), truth.poses[2])
    for index, frame in enumerate(sequence.frames):
        np.testing.assert_array_equal(frame.load(), truth.images[index])
        expected = {o.id: o.boxes[index] for o in truth.objects if np.isfinite(o.boxes[index, 0])}
        assert {o.id for o in frame.objects} == set(expected)
        for obj in frame.objects:
            np.testing.assert_allclose(obj.box, expected[obj.id], atol=1e-9)
            np.testing.assert_allclose(
                obj.polygon, metres_to_pixels(box_corners(expected[obj.id][None])[0], 384), atol=1e-6
            )


# ---------------------------------------------------------------- bad data names the file
def test_missing_png(sim_copy: Path) -> None:
    (sim_copy / "Navtech_Cartesian" / "000004.png").unlink()
    with pytest.raises(FileNotFoundError, match="000004.png"):
        read_sequence(sim_copy)


def test_corrupt_png_header(sim_copy: Path) -> None:
    (sim_copy / "Navtech_Cartesian" / "000002.png").write_bytes(b"this is not a png at all, just text")
    with pytest.raises(ValueError, match="000002.png"):
        read_sequence(sim_copy)


def test_truncated_png_fails_on_load_naming_the_file(sim_copy: Path) -> None:
    path = sim_copy / "Navtech_Cartesian" / "000005.png"
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    sequence = read_sequence(sim_copy)  # the header is intact: detected when the pixels are decoded
    with pytest.raises(ValueError, match="000005.png"):
        sequence.frames[4].load()
    with pytest.raises(FileNotFoundError, match="nothere.png"):
        load_image(sim_copy / "nothere.png")


@pytest.mark.parametrize("text", ['[{"id": 1, "class_name": "car", "bboxes": [', '{"not": "a list"}'])
def test_malformed_annotations_json(sim_copy: Path, text: str) -> None:
    (sim_copy / "annotations" / "annotations.json").write_text(text)
    with pytest.raises(ValueError, match="annotations.json"):
        read_sequence(sim_copy)


def test_malformed_annotation_entry(sim_copy: Path) -> None:
    path = sim_copy / "annotations" / "annotations.json"
    entries = json.loads(path.read_text())
    entries.append({"id": 999, "class_name": "car", "bboxes": [{"position": [1, 2, 3], "rotation": 0.0}]})
    path.write_text(json.dumps(entries))
    with pytest.raises(ValueError, match=r"annotations.json.*id 999"):
        read_sequence(sim_copy)


def test_malformed_meta_json(sim_copy: Path) -> None:
    (sim_copy / "meta.json").write_text('{"set": "test",')
    with pytest.raises(ValueError, match="meta.json"):
        read_sequence(sim_copy)


def test_meta_image_size_must_match_the_scans(sim_copy: Path) -> None:
    meta = json.loads((sim_copy / "meta.json").read_text())
    meta["image_size"] = 1152
    (sim_copy / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="meta.json"):
        read_sequence(sim_copy)


def test_timestamps_file_missing_a_scan(sim_copy: Path) -> None:
    path = sim_copy / "Navtech_Cartesian.txt"
    path.write_text("".join(path.read_text().splitlines(keepends=True)[:-1]))  # 000010.png has no timestamp
    with pytest.raises(ValueError, match=r"Navtech_Cartesian.txt.*000010.png"):
        read_sequence(sim_copy)


def test_timestamps_file_listing_a_missing_scan(sim_copy: Path) -> None:
    path = sim_copy / "Navtech_Cartesian.txt"
    path.write_text(path.read_text() + "Frame: 000011 Time: 1999999999.000000000\n")
    with pytest.raises(FileNotFoundError, match="000011.png"):
        read_sequence(sim_copy)


def test_a_short_nanosecond_field_does_not_break_the_order_of_a_valid_sequence(sim_copy: Path) -> None:
    # RADIATE's logger dropped leading zeros of the nanosecond field: 54000000 ns was printed '54000000' and means
    # 0.054 s. Read as a decimal (float()), frame 2 would be 0.49 s late and frame 4 (5 ns) 0.5 s late.
    path = sim_copy / "Navtech_Cartesian.txt"
    lines = [
        f"Frame: {k:06d} Time: {1574859770 + k}.{ns}"
        for k, ns in zip(
            range(1, 11),
            [
                "900000000",
                "54000000",
                "954000000",
                "5",
                "100000000",
                "200000000",
                "300000000",
                "400000000",
                "500000000",
                "600000000",
            ],
        )
    ]
    path.write_text("\n".join(lines) + "\n")
    (sim_copy / "ego_poses.csv").unlink()
    sequence = read_sequence(sim_copy, estimate_poses=False)
    stamps = [frame.timestamp for frame in sequence.frames]
    assert stamps[1] == pytest.approx(1574859772.054, abs=1e-6)
    assert stamps[3] == pytest.approx(1574859774.000000005, abs=1e-6)
    assert list_frames(sim_copy).timestamp_texts[1] == "1574859772.054000000"


@pytest.mark.parametrize(
    "bad", ["Frame: 000003 Tim: 12.5", "Frame: 000003 Time: 1.0", "Frame: 000003 Time: 12.1234567890"]
)
def test_malformed_or_unordered_timestamps(sim_copy: Path, bad: str) -> None:
    path = sim_copy / "Navtech_Cartesian.txt"
    lines = path.read_text().splitlines()
    lines[2] = bad  # frame 3: malformed, or a time earlier than frame 2's
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"Navtech_Cartesian.txt:3"):
        read_sequence(sim_copy)


@pytest.mark.parametrize(
    "mutate",
    [
        lambda lines: ["frame;timestamp;x;y;yaw"] + lines[1:],  # wrong header
        lambda lines: lines[:3] + [lines[3].replace(lines[3].split(",")[2], "abc")] + lines[4:],  # not a number
        lambda lines: lines[:5] + lines[6:],  # a frame without a pose
        lambda lines: [lines[0]] + [line.replace(line.split(",")[1], "1.5") for line in lines[1:]],  # other timestamps
        lambda lines: lines[:3] + [lines[2]] + lines[3:],  # a frame twice
    ],
    ids=["header", "number", "missing-frame", "timestamps", "duplicate"],
)
def test_bad_ego_poses_csv(sim_copy: Path, mutate) -> None:
    path = sim_copy / "ego_poses.csv"
    path.write_text("\n".join(mutate(path.read_text().splitlines())) + "\n")
    with pytest.raises(ValueError, match="ego_poses.csv"):
        read_sequence(sim_copy)


def test_not_a_sequence_folder(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="Navtech_Cartesian.txt"):
        read_sequence(tmp_path)
    with pytest.raises(FileNotFoundError, match="missing"):
        read_sequence(tmp_path / "missing")


def test_skipped_annotations_are_counted_in_the_log(sim_copy: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = sim_copy / "annotations" / "annotations.json"
    entries = json.loads(path.read_text())
    entries.append({"id": 500, "class_name": "car", "bboxes": [{"position": [10, 10, 0, 5], "rotation": 0.0}] * 2})
    path.write_text(json.dumps(entries))
    with caplog.at_level(logging.WARNING, logger="rafd.data.radiate_files"):
        sequence = read_sequence(sim_copy)
    assert "skipped 2 annotations" in caplog.text and "annotations.json" in caplog.text
    assert all(o.id != 500 for f in sequence.frames for o in f.objects)


def test_annotations_longer_than_the_frames_and_missing_meta(sim_copy: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = sim_copy / "annotations" / "annotations.json"
    entries = json.loads(path.read_text())
    entries.append(
        {
            "id": 777,
            "class_name": "bus",
            "bboxes": [[]] * 2 + [{"position": [100, 100, 10, 40], "rotation": 30.0}] + [[]] * 50,
        }
    )
    path.write_text(json.dumps(entries))
    (sim_copy / "meta.json").unlink()
    with caplog.at_level(logging.WARNING, logger="rafd.data.radiate_files"):
        sequence = read_sequence(sim_copy)
    assert sequence.split is None and sequence.name == "sim_31_0" and "meta.json" in caplog.text
    assert [f.number for f in sequence.frames if any(o.id == 777 for o in f.objects)] == [3]
