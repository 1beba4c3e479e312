"""The virtual laser tracker: measures target centres with Gaussian noise (mm), seedable."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class LaserTracker:
    """Independent Gaussian noise of standard deviation ``sigma_mm`` on every coordinate.

    The seed (section V) uses 0.01 mm. ``rng`` makes a campaign reproducible. ``pose``: where the tracker
    stands, as the pose of the machine's base frame in the tracker frame, ``(R (3, 3), t (3,) mm)``:
    a base-frame point p is reported at ``R p + t`` (None: the tracker reports in the base frame).
    """

    sigma_mm: float = 0.01
    rng: np.random.Generator = field(default_factory=np.random.default_rng)
    pose: tuple[np.ndarray, np.ndarray] | None = None

    def __post_init__(self) -> None:
        if not np.isfinite(self.sigma_mm) or self.sigma_mm < 0:
            raise ValueError(f"tracker noise must be a non-negative number of mm, got {self.sigma_mm}")

    def measure(self, points_mm: np.ndarray) -> np.ndarray:
        """Noisy copies of true target centres (..., 3) given in the base frame, mm, reported in the
        tracker frame (the base frame when :attr:`pose` is None)."""
        points_mm = np.asarray(points_mm, dtype=float)
        if self.pose is not None:
            R, t = self.pose
            points_mm = points_mm @ np.asarray(R, float).T + np.asarray(t, float)
        if self.sigma_mm == 0:
            return points_mm.copy()
        return points_mm + self.rng.normal(0.0, self.sigma_mm, points_mm.shape)


def random_tracker_pose(rng: np.random.Generator, distance_mm=(1000.0, 3000.0), tilt_deg: float = 2.0
                        ) -> tuple[np.ndarray, np.ndarray]:
    """A tracker set up somewhere around the machine: base-in-tracker pose ``(R, t)``.

    The machine's origin lies ``distance_mm`` (uniform range) from the tracker in a random direction
    near its horizon; the tracker is turned by any yaw and tilted by up to ``tilt_deg`` about x and y.
    """
    from scipy.spatial.transform import Rotation

    yaw = rng.uniform(-180.0, 180.0)
    tx, ty = rng.uniform(-tilt_deg, tilt_deg, 2)
    R = Rotation.from_euler("ZYX", [yaw, ty, tx], degrees=True).as_matrix()
    az, el = rng.uniform(0, 2 * np.pi), rng.uniform(-0.3, 0.3)
    d = rng.uniform(*distance_mm)
    t = d * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    return R, t
