"""Window-consistent flip / rotation: images, boxes, poses and targets move together."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from rafd.config import RaFDConfig
from rafd.data.augment import Augmentation, AugmentConfig
from rafd.data.targets import build_targets
from rafd.geometry import (
    box_corners,
    box_polygons_pixels,
    invert_pose,
    metres_to_pixels,
    pixels_to_metres,
    relative_pose,
    transform_points,
)

CFG = RaFDConfig.tiny(input_size=128)
RES = CFG.resolution


def _sorted_rows(points: np.ndarray) -> np.ndarray:
    return points[np.lexsort(points.T[::-1])]


def test_flip_mirrors_box_corners_exactly() -> None:
    boxes = np.array([[3.0, 7.0, 1.8, 4.6, 0.4], [-5.0, -2.0, 2.5, 10.0, -2.8]])
    flipped = Augmentation(flip=True).boxes(boxes)
    np.testing.assert_allclose(flipped[:, 4], -boxes[:, 4])  # yaw -> -yaw
    for original, mirrored in zip(box_corners(boxes), box_corners(flipped)):
        np.testing.assert_allclose(_sorted_rows(mirrored), _sorted_rows(original * [-1.0, 1.0]), atol=1e-12)
    rotated = Augmentation(flip=True, angle=0.3).boxes(boxes)
    for original, moved in zip(box_corners(boxes), box_corners(rotated)):
        g = Augmentation(flip=True, angle=0.3).matrix
        np.testing.assert_allclose(_sorted_rows(moved), _sorted_rows(original @ g.T), atol=1e-12)


SHIFT = dict(shift_px=(100, -40), shift_m=(100 * RES, 40 * RES))


@pytest.mark.parametrize(
    "augmentation",
    [
        Augmentation(True, 0.0),
        Augmentation(False, 0.7),
        Augmentation(True, -2.0),
        Augmentation(False, 0.0, **SHIFT),
        Augmentation(True, 0.5, **SHIFT),
    ],
)
def test_poses_and_points_stay_consistent(augmentation: Augmentation) -> None:
    """A world point seen from every frame: transforming the ego-frame observations into the crop's frame equals
    observing the transformed world with the transformed (shifted-frame) poses; relative motions map by G."""
    rng = np.random.default_rng(3)
    poses = rng.normal(size=(4, 3)) * [20, 20, 1]
    world = rng.normal(size=(5, 2)) * 30
    new_poses = augmentation.poses(poses)
    for t in range(4):
        seen = transform_points(invert_pose(poses[t]), world)
        seen_after = transform_points(invert_pose(new_poses[t]), augmentation.vectors(world))
        np.testing.assert_allclose(augmentation.points(seen), seen_after, atol=1e-9)
    for t in range(1, 4):
        if augmentation.shift_px != (0, 0):
            continue  # a shifted frame moves differently from the ego frame (the observation check above covers it)
        step = relative_pose(poses[t], poses[t - 1])
        new_step = relative_pose(new_poses[t], new_poses[t - 1])
        np.testing.assert_allclose(new_step[:2], augmentation.vectors(step[:2]), atol=1e-9)
        assert new_step[2] == pytest.approx(-step[2] if augmentation.flip else step[2], abs=1e-9)


def _render(boxes: np.ndarray, size: int) -> list[np.ndarray]:
    masks = []
    for polygon in box_polygons_pixels(boxes, size, RES):
        mask = np.zeros((size, size), np.uint8)
        vertices = np.round((polygon - 0.5) * 16).astype(np.int32)  # continuous pixels -> cv2 indices (centres)
        cv2.fillPoly(mask, [vertices], 255, lineType=cv2.LINE_8, shift=4)
        masks.append(mask > 0)
    return masks


@pytest.mark.parametrize(
    "augmentation",
    [Augmentation(True, 0.0), Augmentation(False, 0.5), Augmentation(True, -1.2), Augmentation(False, math.pi / 2)],
)
def test_image_pixels_move_with_the_boxes(augmentation: Augmentation) -> None:
    """Boxes painted into a full 384 px scan; after the augmentation (and the 128 px crop) the painted
    pixels lie where the transformed boxes say."""
    full, crop = 384, 128
    boxes = np.array([[4.0, 6.0, 2.5, 6.0, 0.3], [-6.0, -3.0, 3.0, 5.0, 1.2], [1.0, -7.5, 2.0, 4.5, -0.6]])
    scan = np.zeros((full, full), np.uint8)
    for mask in _render(boxes, full):
        scan[mask] = 255
    image = augmentation.image(scan, crop)
    assert image.shape == (crop, crop) and image.dtype == np.uint8
    painted = image > 127
    expected = np.zeros_like(painted)
    for mask in _render(augmentation.boxes(boxes), crop):
        expected |= mask
    iou = (painted & expected).sum() / (painted | expected).sum()
    assert iou > 0.9, iou  # rasterisation differs along the edges only

    # Each painted blob's centroid is where G takes the source blob's centroid (sub-pixel), and both sit on
    # the (transformed) box centre up to the rasteriser's edge rule.
    def centroids(image: np.ndarray, size: int) -> np.ndarray:
        count, _, _, found = cv2.connectedComponentsWithStats((image > 127).astype(np.uint8))
        assert count == 1 + len(boxes)
        return pixels_to_metres(found[1:] + 0.5, size, RES)  # cv2 indices -> continuous pixels -> metres

    source, moved = augmentation.points(centroids(scan, full)), centroids(image, crop)
    for point in moved:
        assert np.min(np.hypot(*(source - point).T)) < 0.1 * RES
        assert np.min(np.hypot(*(augmentation.boxes(boxes)[:, :2] - point).T)) < 0.5 * RES
    if augmentation.angle == 0.0:  # a pure flip is an exact column reversal of the crop
        identity = Augmentation().image(scan, crop)
        np.testing.assert_array_equal(image, identity[:, ::-1])


def _targets(boxes, ids, poses):
    return build_targets(boxes, ids, poses, CFG)


@pytest.fixture(scope="module")
def window():
    """Three frames: ego turning, one object moving, one static, one appearing."""
    poses = np.array([[0.0, 0.0, 0.1], [0.3, 2.0, 0.16], [0.7, 4.1, 0.25]])
    boxes = [
        np.array([[3.1, 5.2, 1.8, 4.6, 0.3], [-6.0, 2.0, 2.0, 4.4, 1.0]]),
        np.array([[2.6, 4.0, 1.8, 4.6, 0.33], [-5.7, 0.1, 2.0, 4.4, 1.02], [6.0, -6.0, 2.2, 5.0, -0.4]]),
        np.array([[2.0, 2.5, 1.8, 4.6, 0.35], [-5.5, -2.0, 2.0, 4.4, 1.05], [6.2, -7.1, 2.2, 5.0, -0.4]]),
    ]
    ids = [np.array([1, 2]), np.array([1, 2, 3]), np.array([1, 2, 3])]
    return boxes, ids, poses


@pytest.mark.parametrize(
    "augmentation",
    [
        Augmentation(True, 0.0),
        Augmentation(False, math.pi / 2),
        Augmentation(False, math.pi),
        Augmentation(True, -math.pi / 2),
    ],
    ids=["flip", "rot90", "rot180", "flip-rot270"],
)
def test_targets_of_augmented_annotations_equal_augmented_targets(window, augmentation: Augmentation) -> None:
    boxes, ids, poses = window
    original = _targets(boxes, ids, poses)
    augmented = _targets([augmentation.boxes(b) for b in boxes], ids, augmentation.poses(poses))
    size = CFG.feature_size
    np.testing.assert_allclose(augmented["heatmap"], augmentation.grid(original["heatmap"]), atol=1e-6)
    np.testing.assert_allclose(augmented["flow"], augmentation.flow(original["flow"]), atol=1e-5)
    np.testing.assert_array_equal(augmented["flow_valid"], augmentation.grid(original["flow_valid"]))
    np.testing.assert_array_equal(augmented["flow_foreground"], augmentation.grid(original["flow_foreground"]))
    assert original["flow_foreground"].sum() > 0 and original["flow_valid"].min() == 0.0  # non-trivial maps
    # Regression targets: the same objects, their cells moved by G, offsets turned by G, yaw mapped.
    mask = original["box_mask"] > 0
    np.testing.assert_array_equal(augmented["box_mask"], original["box_mask"])
    rows, cols = np.divmod(original["centre_index"][mask], size)
    moved = augmentation.grid(np.arange(size * size).reshape(size, size))  # cell id now at each position
    lookup = {int(v): int(k) for k, v in enumerate(moved.reshape(-1))}
    np.testing.assert_array_equal(
        augmented["centre_index"][mask], [lookup[int(r * size + c)] for r, c in zip(rows, cols)]
    )
    np.testing.assert_allclose(augmented["offset"][mask], augmentation.vectors(original["offset"][mask]), atol=1e-5)
    np.testing.assert_allclose(augmented["log_size"], original["log_size"])
    np.testing.assert_allclose(augmented["boxes"][mask], augmentation.boxes(original["boxes"][mask]), atol=1e-5)


def test_arbitrary_rotation_turns_the_object_flow(window) -> None:
    boxes, ids, poses = window
    augmentation = Augmentation(True, 0.4)
    original = _targets(boxes, ids, poses)
    augmented = _targets([augmentation.boxes(b) for b in boxes], ids, augmentation.poses(poses))
    for pair in range(2):
        for k in range(len(boxes[pair + 1])):
            if ids[pair + 1][k] not in ids[pair]:
                continue
            row, col = _cell_of(boxes[pair + 1][k])
            before = original["flow"][pair, :, row, col]
            row, col = _cell_of(augmentation.boxes(boxes[pair + 1][k : k + 1])[0])
            after = augmented["flow"][pair, :, row, col]
            np.testing.assert_allclose(after, augmentation.vectors(before), atol=1e-5)
            assert np.linalg.norm(before) > 0.1


def _cell_of(box: np.ndarray) -> tuple[int, int]:
    size = CFG.feature_size
    return int(math.floor(size / 2 - box[1] / CFG.cell_size)), int(math.floor(box[0] / CFG.cell_size + size / 2))


def test_sampling_is_seeded_and_bounded() -> None:
    config = AugmentConfig(flip_probability=0.5, max_rotation_deg=10.0)
    draws = [Augmentation.sample(np.random.default_rng(s), config) for s in range(200)]
    assert draws[:5] == [Augmentation.sample(np.random.default_rng(s), config) for s in range(5)]
    assert 60 < sum(d.flip for d in draws) < 140
    assert max(abs(d.angle) for d in draws) <= math.radians(10.0)
    with pytest.raises(ValueError):
        AugmentConfig(flip_probability=1.5)


# ---------------------------------------------------------------- intensity
def test_intensity_changes_are_what_they_say_and_leave_neutral_windows_alone() -> None:
    from rafd.data.augment import AugmentConfig

    rng = np.random.default_rng(0)
    frames = rng.integers(0, 200, (4, 32, 32)).astype(np.uint8)
    assert Augmentation().intensity(frames) is frames or np.array_equal(Augmentation().intensity(frames), frames)
    gained = Augmentation(gain=1.25).intensity(frames)
    np.testing.assert_allclose(gained, np.clip(np.rint(frames / 255.0 * 1.25 * 255), 0, 255), atol=1)
    gamma = Augmentation(gamma=1.2).intensity(frames)
    np.testing.assert_allclose(gamma, np.rint(255 * (frames / 255.0) ** 1.2), atol=1)
    floor = Augmentation(floor=12.0, noise_seed=3).intensity(np.zeros((2, 64, 64), np.uint8))
    assert 6 < floor.mean() < 16 and floor.std() > 2  # a speckled floor of ~12 grey
    np.testing.assert_array_equal(
        floor, Augmentation(floor=12.0, noise_seed=3).intensity(np.zeros((2, 64, 64), np.uint8))
    )
    blurred = Augmentation(blur=0.9).intensity(frames)
    assert blurred.std() < frames.std()
    # one window, one change: frame-to-frame differences come from the jitter only
    jittered = Augmentation(gain=1.1, jitter=0.05, noise_seed=1).intensity(np.full((4, 8, 8), 100, np.uint8))
    assert np.all(np.abs(jittered.astype(int) - 110) < 20) and len({int(f[0, 0]) for f in jittered}) > 1
    with pytest.raises(ValueError, match="gain_range"):
        AugmentConfig(gain_range=(0.0, 1.0))


def test_sampled_intensity_follows_the_config() -> None:
    from rafd.data.augment import AugmentConfig

    rng = np.random.default_rng(1)
    off = [Augmentation.sample(rng, AugmentConfig()) for _ in range(50)]
    assert not any(a.changes_intensity for a in off)
    config = AugmentConfig(intensity_probability=1.0)
    drawn = [Augmentation.sample(rng, config) for _ in range(200)]
    gains = np.array([a.gain for a in drawn])
    assert all(a.changes_intensity for a in drawn) and gains.min() >= 0.6 and gains.max() <= 1.6
    assert gains.min() < 0.7 and gains.max() > 1.4 and all(0 <= a.floor <= 14 and 0 <= a.blur <= 0.9 for a in drawn)


def test_a_shifted_crop_shows_its_boxes_where_the_scan_has_them() -> None:
    """A bright square at a known ego position: in the shifted (and turned) crop it lies under the augmented box."""
    scan = np.zeros((1152, 1152), np.uint8)
    box = np.array([[30.0, -20.0, 3.0, 3.0, 0.0]])  # metres: 30 m right, 20 m behind
    u, v = metres_to_pixels(box[0, :2], 1152, RES)
    scan[int(v) - 8 : int(v) + 9, int(u) - 8 : int(u) + 9] = 255
    for augmentation in (
        Augmentation(False, 0.0, shift_px=(150, 120), shift_m=(150 * RES, -120 * RES)),
        Augmentation(True, 0.6, shift_px=(150, 120), shift_m=(150 * RES, -120 * RES)),
    ):
        crop = augmentation.image(scan, 128)
        moved = augmentation.boxes(box)[0]
        cu, cv = metres_to_pixels(moved[:2], 128, RES)
        ys, xs = np.nonzero(crop > 128)
        assert len(xs) > 100 and abs(xs.mean() + 0.5 - cu) < 1.0 and abs(ys.mean() + 0.5 - cv) < 1.0
    with pytest.raises(ValueError, match="leaves"):
        Augmentation(shift_px=(560, 0), shift_m=(560 * RES, 0.0)).image(scan, 128)


def test_the_shipped_recipe_augmentation_always_fits_a_radiate_scan() -> None:
    """Shifted (full-scan tile) and turned crops of 256 px must fit inside a 1152 px scan for every draw."""
    from rafd.train.recipes import recipe_config

    recipe = recipe_config("default")
    scan = np.zeros((1152, 1152), np.uint8)
    rng = np.random.default_rng(0)
    shifted = 0
    for _ in range(300):
        augmentation = Augmentation.sample(rng, recipe.data.augment, RES)
        assert augmentation.image(scan, recipe.model.input_size).shape == (256, 256)
        shifted += augmentation.shift_px != (0, 0)
    assert 120 < shifted < 240  # about 60% of the windows are cut away from the radar
