import numpy as np
import pytest

from rafd import geometry as g


def test_pixel_metre_round_trip_and_axes():
    uv = np.array([[576.0, 576.0], [586.0, 566.0]])
    xy = g.pixels_to_metres(uv, 1152)
    np.testing.assert_allclose(xy[0], [0.0, 0.0])
    # 10 px right and 10 px up is +x (right) and +y (forward)
    np.testing.assert_allclose(xy[1], [10 * g.RADIATE_RESOLUTION, 10 * g.RADIATE_RESOLUTION])
    np.testing.assert_allclose(g.metres_to_pixels(xy, 1152), uv)


def test_radiate_box_reproduces_sdk_polygon():
    rng = np.random.default_rng(0)
    for _ in range(50):
        position = rng.uniform([0, 0, 5, 5], [1100, 1100, 60, 90])
        rotation = rng.uniform(-360, 360)
        box = g.radiate_to_box(position, rotation)
        np.testing.assert_allclose(
            g.box_polygons_pixels(box[None], 1152)[0], g.radiate_polygon(position, rotation), atol=1e-9
        )
        back_position, back_rotation = g.box_to_radiate(box)
        np.testing.assert_allclose(back_position, position, atol=1e-9)
        assert back_rotation == pytest.approx(rotation)


def test_box_corners_convention():
    # width 2 along x, length 4 along y, rotated 90 degrees counter-clockwise: long side along x
    corners = g.box_corners(np.array([[1.0, 2.0, 2.0, 4.0, np.pi / 2]]))[0]
    np.testing.assert_allclose(corners.min(0), [1 - 2, 2 - 1], atol=1e-12)
    np.testing.assert_allclose(corners.max(0), [1 + 2, 2 + 1], atol=1e-12)


def test_se2_relative_pose():
    rng = np.random.default_rng(1)
    for _ in range(20):
        a, b = rng.normal(size=3) * [10, 10, 2], rng.normal(size=3) * [10, 10, 2]
        points = rng.normal(size=(7, 2)) * 20
        rel = g.relative_pose(a, b)
        expected = g.transform_points(g.invert_pose(b), g.transform_points(a, points))
        np.testing.assert_allclose(g.transform_points(rel, points), expected, atol=1e-9)
        np.testing.assert_allclose(g.compose_poses(a, g.invert_pose(a)), [0, 0, 0], atol=1e-12)


def test_centre_crop_keeps_radar_at_centre():
    image = np.zeros((1152, 1152), np.uint8)
    image[576, 576] = 255  # the pixel covering [576, 577) x [576, 577)
    crop = g.centre_crop(image, 256)
    assert crop.shape == (256, 256) and crop[128, 128] == 255
    with pytest.raises(ValueError):
        g.centre_crop(image, 2000)


def test_feature_cell_centres():
    centres = g.feature_cell_centres(4, 16, 0.5)
    # cell (0, 0) covers pixels [0, 4): centre pixel (2, 2) -> x = (2 - 8) * 0.5, y = (8 - 2) * 0.5
    np.testing.assert_allclose(centres[0, 0], [-3.0, 3.0])
    np.testing.assert_allclose(centres[3, 3], [3.0, -3.0])
