"""Radar scatterers: the point reflectors the sensor model illuminates (static world and road users)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import cast

import numpy as np


@dataclass(frozen=True)
class Scatterers:
    """Point reflectors; `normal` is zero for isotropic ones; `owner` is -1 for static world, else a road user's
    index; `diffuse` ones add up in power within a polar cell (extended, partly filled returns such as vehicles),
    the others keep the cell's strongest (rafd.sim.sensor.NavtechSensor.accumulate)."""

    xy: np.ndarray  # [N, 2] metres
    amplitude: np.ndarray  # [N] power relative to the noise floor
    normal: np.ndarray  # [N, 2] unit outward normal, or 0
    occluder: np.ndarray  # [N] bool: casts a radar shadow behind it
    owner: np.ndarray  # [N] int
    # [N] bool; None = none diffuse (__post_init__ puts zeros in its place, so it is an array once constructed)
    diffuse: np.ndarray = field(default=cast("np.ndarray", None))

    def __post_init__(self) -> None:
        if self.diffuse is None:
            object.__setattr__(self, "diffuse", np.zeros(len(self.xy), bool))

    def __len__(self) -> int:
        return len(self.xy)

    @staticmethod
    def concat(parts: list[Scatterers]) -> Scatterers:
        return Scatterers(
            xy=np.concatenate([p.xy for p in parts]).reshape(-1, 2),
            amplitude=np.concatenate([p.amplitude for p in parts]),
            normal=np.concatenate([p.normal for p in parts]).reshape(-1, 2),
            occluder=np.concatenate([p.occluder for p in parts]),
            owner=np.concatenate([p.owner for p in parts]),
            diffuse=np.concatenate([p.diffuse for p in parts]),
        )

    def subset(self, keep: np.ndarray) -> Scatterers:
        return Scatterers(
            self.xy[keep],
            self.amplitude[keep],
            self.normal[keep],
            self.occluder[keep],
            self.owner[keep],
            self.diffuse[keep],
        )
