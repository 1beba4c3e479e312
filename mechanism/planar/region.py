"""Where calibration positions of the planar robot may lie and what the machine allows there."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pmcal.mechanism.planar.geometry import Geometry
from pmcal.mechanism.planar.kinematics import Q, directions, inverse


@dataclass(frozen=True)
class Region:
    """Where calibration positions may lie (mm, seed frame) and what the machine allows there.

    x, y : (min, max) of a box; ``min_transmission``: smallest |sin| of the angle between proximal and
    distal link of each limb (away from the workspace boundary singularity); ``min_platform``: smallest
    |sin| of the angle between the two distal links (away from the platform singularity);
    ``scale_range``: the linear scale's range l0 (mm), which the mechanism lengths must fit in.
    """

    x: tuple[float, float]
    y: tuple[float, float]
    min_transmission: float = 0.3
    min_platform: float = 0.3
    scale_range: float = 350.0

    def candidates(self, geom: Geometry, step: float) -> np.ndarray:
        """Grid points (N, 2) of the box that the robot reaches with the required transmission."""
        xs = np.arange(self.x[0], self.x[1] + 1e-9, step)
        ys = np.arange(self.y[0], self.y[1] + 1e-9, step)
        r = np.stack(np.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)
        theta = inverse(geom, r)
        ok = np.all(np.isfinite(theta), axis=1)
        r, theta = r[ok], theta[ok]
        u, w = directions(geom, r, theta)
        trans = np.abs(np.einsum("kij,jl,kil->ki", w, Q, u)).min(axis=1)
        plat = np.abs(np.linalg.det(w))
        return r[(trans >= self.min_transmission) & (plat >= self.min_platform)]
