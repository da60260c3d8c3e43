"""Which road users the simulated annotator boxes: the unshadowed ones, and shadowed ones the scan still shows."""

from __future__ import annotations

import math

import numpy as np

from rafd.sim.scene import Scatterers
from rafd.sim.sensor import NavtechSensor
from rafd.sim.sequence import MIN_SHADOWED_STRENGTH, annotator_sees, visible_beams
from rafd.sim.vehicles import Look, diffuse_returns


def test_the_rule_boxes_unshadowed_road_users_and_shadowed_ones_still_strong() -> None:
    lit, seen = np.array([3, 0, 0, 0]), np.array([10, 10, 10, 0])
    strength = np.array([0.1, 4.0 * MIN_SHADOWED_STRENGTH, 2.0 * MIN_SHADOWED_STRENGTH, 9.0])
    # 30% lit: boxed however faint; wholly shadowed (shadow 0.25): boxed only if 0.25 x strength reaches the faintest
    # unshadowed strength; never seen by any beam: not boxed
    assert annotator_sees(lit, seen, strength, shadow=0.25).tolist() == [True, True, False, False]


def test_a_car_behind_another_is_boxed_when_its_shadowed_return_shows() -> None:
    sensor = NavtechSensor(512)
    rng = np.random.default_rng(0)
    azimuth_bin = 2.0 * math.pi / sensor.config.azimuths
    near, far = np.array([0.0, 10.0, 1.9, 4.5, 0.0]), np.array([0.0, 17.0, 1.9, 4.5, 0.0])  # one behind the other
    look = Look(strength=2.0, visible=(1.0, 0.0, 1.0, 0.0), spread=0.3, glints=0)
    parts = [
        diffuse_returns(box, look, rng, owner, azimuth_bin, sensor.config.range_bin)
        for owner, box in enumerate((near, far))
    ]
    echoes = sensor.illuminate(Scatterers.concat(parts))
    lit, seen = visible_beams(echoes, 2, sensor.config.azimuths)
    assert lit[0] == seen[0] > 0 and lit[1] == 0 < seen[1]  # the far car is wholly in the near one's shadow
    shadowed = echoes.power[echoes.owner == 1].sum() / echoes.power[echoes.owner == 0].sum()
    # rendered faint, at the sensor's shadow (0.25) of its power; above 0.25 because the near car's far side is
    # in its own shadow too
    assert 0.1 < shadowed < 0.5
    strong, faint = (
        4.0 * MIN_SHADOWED_STRENGTH / sensor.config.shadow,
        0.5 * MIN_SHADOWED_STRENGTH / sensor.config.shadow,
    )
    assert annotator_sees(lit, seen, np.array([0.1, strong]), sensor.config.shadow).tolist() == [True, True]
    assert annotator_sees(lit, seen, np.array([0.1, faint]), sensor.config.shadow).tolist() == [True, False]
