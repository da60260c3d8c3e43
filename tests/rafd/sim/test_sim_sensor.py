"""Navtech sensor model: geometry of the polar->Cartesian warp, occlusion, noise floor, transient returns."""

from __future__ import annotations

import numpy as np
import pytest

from rafd.geometry import metres_to_pixels
from rafd.sim.scene import Scatterers
from rafd.sim.sensor import Difficulty, NavtechSensor
from rafd.sim.sequence import _transient_returns, world_clutter


def _points(xy, amplitude, occluder=False) -> Scatterers:
    xy = np.asarray(xy, float).reshape(-1, 2)
    n = len(xy)
    return Scatterers(xy, np.full(n, float(amplitude)), np.zeros((n, 2)), np.full(n, occluder), np.full(n, -1))


def test_point_target_lands_on_its_pixel() -> None:
    sensor = NavtechSensor(512)
    sensor.mount = np.zeros_like(sensor.mount)  # the fixed mounting pattern near the radar outshines a far point
    quiet = Difficulty(clutter=0.0, ghosts=0.0, noise=0.0)
    for xy in [(10.0, 20.0), (-25.0, -5.0), (3.0, -30.0)]:
        echoes = sensor.illuminate(_points(xy, 400.0))
        image = sensor.to_cartesian(
            sensor.receive(
                sensor.accumulate(echoes.azimuth, echoes.ranges, echoes.power), np.random.default_rng(0), quiet
            )
        )
        v, u = np.unravel_index(np.argmax(image), image.shape)
        expected = metres_to_pixels(np.array(xy), 512)
        assert np.hypot(u + 0.5 - expected[0], v + 0.5 - expected[1]) < 2.5, (xy, (u, v), expected)


def test_occluder_shadows_what_is_behind_it() -> None:
    sensor = NavtechSensor(512)
    echoes = sensor.illuminate(
        Scatterers.concat(
            [_points((0.0, 10.0), 50.0, occluder=True), _points((0.0, 20.0), 50.0), _points((10.0, 0.0), 50.0)]
        )
    )
    assert echoes.lit.tolist() == [True, False, True]
    assert echoes.power[1] < 0.5 * echoes.power[2]


def test_back_faces_are_invisible() -> None:
    sensor = NavtechSensor(256)
    facing = Scatterers(
        np.array([[0.0, 10.0], [0.0, 12.0]]),
        np.ones(2),
        np.array([[0.0, -1.0], [0.0, 1.0]]),
        np.zeros(2, bool),
        np.zeros(2, int),
    )
    assert len(sensor.illuminate(facing).ranges) == 1


def test_noise_floor_and_disc() -> None:
    sensor = NavtechSensor(1152)
    image = sensor.to_cartesian(
        sensor.receive(np.zeros((400, sensor.num_bins)), np.random.default_rng(1), Difficulty())
    )
    assert image[0, 0] == 0 and image[-1, -1] == 0  # outside the 100 m disc
    ring = image[576, 700:1000]
    assert 5 < np.median(ring) < 40 and ring.std() > 3  # speckled floor, not constant
    louder = sensor.to_cartesian(
        sensor.receive(np.zeros((400, sensor.num_bins)), np.random.default_rng(1), Difficulty(noise=4.0))
    )
    assert np.median(louder[576, 700:1000]) > 1.5 * np.median(ring)


def test_clutter_and_ghosts_change_every_frame() -> None:
    sensor = NavtechSensor(512)
    rng = np.random.default_rng(5)
    vehicle = (np.full(20, 100.0), np.linspace(20.0, 22.0, 20), np.full(20, 50.0))
    first = _transient_returns(rng, sensor, Difficulty(ghosts=4.0), 0.0, [vehicle])
    second = _transient_returns(rng, sensor, Difficulty(ghosts=4.0), 0.0, [vehicle])
    assert len(first[0]) > 100 and len(second[0]) > 100
    assert not np.array_equal(first[1][:50], second[1][:50])
    ghost_first = first[1][np.abs(first[0] - 100.0) < 3.0]
    assert np.any(ghost_first > 22.5)  # a ghost behind the vehicle (longer multipath)
    none = _transient_returns(np.random.default_rng(5), sensor, Difficulty(clutter=0.0, ghosts=0.0), 0.0, [vehicle])
    assert len(none[0]) == 0
    persistent = _transient_returns(np.random.default_rng(5), sensor, Difficulty(ghosts=0.0), 1.0, [vehicle])
    assert len(persistent[0]) == 0  # all the clutter is fixed in the world (world_clutter)


def test_world_clutter_has_the_transient_density_and_its_persistent_share() -> None:
    """Per m^2 as many clutter points as _transient_returns draws per scan (600 per 100 m disc), times the share."""
    bounds = (-100.0, 100.0, -100.0, 100.0)
    rng = np.random.default_rng(6)
    xy, power = world_clutter(rng, bounds, Difficulty(), 1.0)
    expected = 600 * 200.0**2 / (np.pi * 100.0**2)  # points, besides the bursts' 10-40 each
    assert expected < len(xy) < expected + 3 * 8 * 40 * 200.0**2 / (np.pi * 100.0**2)
    assert np.all(np.abs(xy) < 110.0) and np.all(power > 0)
    half, _ = world_clutter(np.random.default_rng(6), bounds, Difficulty(), 0.5)
    assert 0.35 * len(xy) < len(half) < 0.65 * len(xy)
    assert len(world_clutter(rng, bounds, Difficulty(), 0.0)[0]) == 0
    assert len(world_clutter(rng, bounds, Difficulty(clutter=0.0), 1.0)[0]) == 0


def test_forced_weather_and_unknown_weather() -> None:
    from rafd.sim.sensor import WEATHERS, Conditions

    drawn = {Conditions.sample(np.random.default_rng(seed)).weather for seed in range(40)}
    assert drawn == set(WEATHERS)  # drawn per drive when not forced
    for weather in WEATHERS:
        conditions = [Conditions.sample(np.random.default_rng(seed), weather) for seed in range(10)]
        assert {c.weather for c in conditions} == {weather}
        assert all((c.rain > 0) == (weather == "rain") for c in conditions)
        assert all((c.attenuation == 0.0) == (weather == "clear") for c in conditions)
    with pytest.raises(ValueError, match="weather must be one of"):
        Conditions.sample(np.random.default_rng(0), "snow")


def test_forcing_the_weather_keeps_the_drive() -> None:
    """A forced weather changes only the weather's own draws: every other condition, and the generator's state for
    the rest of the drive (town, traffic, scans), are those of the drive as drawn; forcing the weather it drew
    changes nothing."""
    from rafd.sim.sensor import WEATHERS, Conditions

    kept = ("gain", "floor_near", "floor_far", "striping", "speckle_grain", "clutter_persistence", "beam_seed")
    for seed in range(30):
        drawn_rng = np.random.default_rng(seed)
        drawn = Conditions.sample(drawn_rng)
        after_drawn = drawn_rng.random(4)
        for weather in WEATHERS:
            forced_rng = np.random.default_rng(seed)
            forced = Conditions.sample(forced_rng, weather)
            np.testing.assert_array_equal(forced_rng.random(4), after_drawn)
            assert all(getattr(forced, name) == getattr(drawn, name) for name in kept)
            assert (forced == drawn) == (weather == drawn.weather)


def test_forced_weather_simulates_the_same_drive() -> None:
    """`rafd-simulate --weather W` renders the drives it would draw, in W (not other drives)."""
    from rafd.sim.sequence import run_simulation

    drawn = run_simulation(11, 2, "test", 64, Difficulty(), "a")
    for weather in {"clear", "fog", "rain"} - {drawn.conditions.weather}:
        forced = run_simulation(11, 2, "test", 64, Difficulty(), "b", weather=weather)
        np.testing.assert_array_equal(forced.poses, drawn.poses)
        np.testing.assert_array_equal(forced.timestamps_ns, drawn.timestamps_ns)
        assert forced.conditions.weather == weather and forced.conditions.gain == drawn.conditions.gain


def test_far_structure_is_not_dimmed_by_range() -> None:
    """Real structure 40 m away is about as bright as at 10 m (rafd.sim.realism's rings): the same point at 40 m
    keeps at least 95% of its power at 10 m."""
    sensor = NavtechSensor(1152)
    echoes = sensor.illuminate(_points([[0.0, 10.0], [0.0, 40.0]], 100.0))
    near, far = echoes.power[np.argsort(echoes.ranges)]
    assert far >= 0.95 * near
