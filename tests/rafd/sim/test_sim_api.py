"""simulate_sequence / simulate_dataset: determinism, RADIATE format, ground truth round trip, dynamics."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import numpy as np
import pytest

from rafd.geometry import radiate_to_box, relative_pose
from rafd.sim import Difficulty, sequence_seed, simulate_dataset, simulate_sequence
from rafd.sim.sequence import run_simulation
from rafd.sim.writer import write_sequence

SIZE = 384


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory):
    """(in-memory truth, folder) of one 30-frame sequence."""
    sequence = run_simulation(12, 30, "test", SIZE, Difficulty(), name="sim_12_0")  # a drive with traffic
    return sequence, write_sequence(sequence, tmp_path_factory.mktemp("sim") / "sim_12_0")


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_same_seed_gives_identical_bytes_and_other_seed_differs(tmp_path: Path) -> None:
    first = simulate_sequence(tmp_path / "a" / "seq", seed=3, num_frames=4, split="test", size=256)
    second = simulate_sequence(tmp_path / "b" / "seq", seed=3, num_frames=4, split="test", size=256)
    other = simulate_sequence(tmp_path / "c" / "seq", seed=4, num_frames=4, split="test", size=256)
    assert _files(first) == _files(second)
    assert _files(first)["Navtech_Cartesian/000001.png"] != _files(other)["Navtech_Cartesian/000001.png"]


def test_dataset_names_and_derived_seeds(tmp_path: Path) -> None:
    paths = simulate_dataset(tmp_path, sequences=2, frames=2, seed=9, split="train_good_and_bad_weather", size=128)
    assert [p.name for p in paths] == ["sim_9_0", "sim_9_1"]
    metas = [json.loads((p / "meta.json").read_text()) for p in paths]
    assert [m["seed"] for m in metas] == [sequence_seed(9, 0), sequence_seed(9, 1)]
    assert metas[0]["seed"] != metas[1]["seed"]
    assert all(m["set"] == "train_good_and_bad_weather" and m["name"] == p.name for m, p in zip(metas, paths))


def test_radiate_layout(simulated) -> None:
    sequence, folder = simulated
    names = sorted(p.name for p in (folder / "Navtech_Cartesian").iterdir())
    assert names == [f"{k:06d}.png" for k in range(1, 31)]
    lines = (folder / "Navtech_Cartesian.txt").read_text().splitlines()
    assert len(lines) == 30
    stamps = []
    for k, line in enumerate(lines, start=1):
        match = re.fullmatch(r"Frame: (\d{6}) Time: (\d{10})\.(\d{9})", line)
        assert match and int(match.group(1)) == k, line
        stamps.append(int(match.group(2)) + int(match.group(3)) * 1e-9)
    periods = np.diff(stamps)
    assert 1.5e9 < stamps[0] < 1.6e9
    assert np.all((periods > 0.2) & (periods < 0.27)) and periods.std() > 1e-4  # ~4 Hz with jitter
    meta = json.loads((folder / "meta.json").read_text())
    assert meta["name"] == "sim_12_0" and meta["set"] == "test" and meta["type"] == "simulated"
    annotations = json.loads((folder / "annotations" / "annotations.json").read_text())
    assert annotations and all(set(o) == {"id", "class_name", "bboxes"} and len(o["bboxes"]) == 30 for o in annotations)
    for entry in (b for o in annotations for b in o["bboxes"]):
        assert entry == [] or (set(entry) == {"position", "rotation"} and len(entry["position"]) == 4)
    with (folder / "ego_poses.csv").open() as handle:
        rows = list(csv.reader(handle))
    assert rows[0] == ["frame", "timestamp", "x", "y", "yaw"]
    assert [int(r[0]) for r in rows[1:]] == list(range(1, 31))
    assert np.allclose([float(r[1]) for r in rows[1:]], stamps, atol=1e-6)
    assert np.allclose(np.array(rows[1:], dtype=float)[:, 2:], sequence.poses)


def test_annotations_round_trip_to_true_boxes(simulated) -> None:
    sequence, folder = simulated
    annotations = {o["id"]: o for o in json.loads((folder / "annotations" / "annotations.json").read_text())}
    assert sorted(annotations) == sorted(o.id for o in sequence.objects)
    for obj in sequence.objects:
        assert annotations[obj.id]["class_name"] == obj.class_name
        for truth, entry in zip(obj.boxes, annotations[obj.id]["bboxes"]):
            if np.isnan(truth[0]):
                assert entry == []
            else:
                box = radiate_to_box(entry["position"], entry["rotation"], image_size=SIZE)
                np.testing.assert_allclose(box, truth, atol=1e-9)
                assert np.all(np.abs(truth[:2]) < SIZE / 2 * 0.173611)  # centre inside the scan


def test_ego_speed_and_yaw_rate_vary(simulated) -> None:
    sequence, _ = simulated
    dt = np.diff(sequence.timestamps_ns) / 1e9
    steps = np.stack([relative_pose(sequence.poses[k + 1], sequence.poses[k]) for k in range(29)])  # [29, 3]
    speed = np.hypot(steps[:, 0], steps[:, 1]) / dt
    yaw_rate = steps[:, 2] / dt
    assert 0.0 <= speed.min() and speed.max() < 16.0
    assert speed.std() > 0.2 and yaw_rate.std() > 0.005
    assert np.all(np.abs(steps[:, 0]) < np.abs(steps[:, 1]) + 0.05)  # driving forward (ego y), not sideways


def test_objects_enter_and_leave_with_realistic_classes(simulated) -> None:
    sequence, _ = simulated
    present = np.array([np.isfinite(o.boxes[:, 0]) for o in sequence.objects])  # [N, T]
    assert present.all(0).sum() < len(sequence.objects)
    assert np.any(~present[:, 0] & present[:, -1]) or np.any(
        present[:, 0] & ~present[:, -1]
    )  # someone enters or leaves
    sizes = {o.class_name: np.nanmax(o.boxes[:, 2:4]) for o in sequence.objects}  # the long side, however labelled
    assert set(sizes) <= {"car", "van", "truck", "bus", "motorbike", "bicycle", "pedestrian", "group_of_pedestrians"}
    if "car" in sizes:
        assert 4.2 < sizes["car"] < 6.5  # the body (4.0-4.9 m) and the blur an annotator draws around


def test_traffic_mix_moving_parked_oncoming() -> None:
    from rafd.sim.city import Street, build_city
    from rafd.sim.road import drive_ego, make_route
    from rafd.sim.traffic import spawn_traffic

    rng = np.random.default_rng(21)
    times = np.arange(40) * 0.25
    street = Street(axis=1, position=1.65, lanes=1, pavement=3.0)
    city = build_city(rng, (-260.0, 260.0, -160.0, 360.0), street, parked_density=1.0)
    route = make_route(street.position, -300.0, 400.0, lanes=1)
    ego = drive_ego(rng, route, times, 1.65)
    agents = spawn_traffic(rng, city, route, times, ego.s, 1.65, 100.0, density=1.0)
    speeds = np.array([np.hypot(*np.diff(a.boxes[:, :2], axis=0).T).max() / 0.25 for a in agents])
    moving = speeds > 0.5
    assert np.any(~moving) and np.any(moving)  # parked and driving
    headings = {
        round(float(np.cos(a.boxes[0, 4])), 0) for a, m in zip(agents, moving) if m and a.class_name != "pedestrian"
    }
    assert {1.0, -1.0} <= headings  # both ways along the ego's street
    assert speeds.max() <= 15.0 + 1e-6
    assert len({a.id for a in agents}) == len(agents)


def test_routes_turn_into_the_crossing_street() -> None:
    from rafd.sim.road import make_route

    route = make_route(1.65, -50.0, 150.0, lanes=1, turn=-1, junction_y=60.0, radius=10.0)
    end_point, end_heading = route.points[-1], route.heading[-1]
    assert abs(end_point[1] - 60.0) < 0.3 and abs(np.cos(end_heading) - 1.0) < 1e-3  # eastbound on y = 60
    start = route.frame_at(np.array(0.0), 0.0)[0]
    np.testing.assert_allclose(start, [1.65, 0.0], atol=1e-6)


def test_labels_carry_the_annotators_ambiguity_and_cover_the_same_rectangles() -> None:
    """Within one track, labels flip yaw by 180 degrees and swap width/length, as RADIATE's do; the rectangles (and
    the scans) are those of the exact labelling."""
    from rafd.geometry import box_corners
    from rafd.sim import Difficulty
    from rafd.sim.sequence import run_simulation

    exact = run_simulation(27, 8, "test", 256, Difficulty(), name="a", ambiguous=False)
    labelled = run_simulation(27, 8, "test", 256, Difficulty(), name="a", ambiguous=True)
    assert all(np.array_equal(a, b) for a, b in zip(exact.images, labelled.images))
    swaps = flips = 0
    for e, a in zip(exact.objects, labelled.objects):
        for box_e, box_a in zip(e.boxes, a.boxes):
            if not np.isfinite(box_e[0]):
                assert not np.isfinite(box_a[0])
                continue
            ce, ca = box_corners(box_e)[0], box_corners(box_a)[0]
            assert np.linalg.norm(ce[:, None] - ca[None], axis=-1).min(axis=1).max() < 1e-9  # same rectangle
            swapped = not np.isclose(box_e[2], box_a[2])
            swaps += swapped
            turn = (box_a[4] - box_e[4] - (np.pi / 2 if swapped else 0.0)) % (2 * np.pi)
            flips += bool(np.isclose(turn, np.pi))
    assert swaps > 5 and flips > 5
