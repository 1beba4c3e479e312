"""The virtual laser tracker: measures target centres with Gaussian noise (mm), seedable."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class LaserTracker:
    """Independent Gaussian noise of standard deviation ``sigma_mm`` on every coordinate.

    The seed (section V) uses 0.01 mm. ``rng`` makes a campaign reproducible.
    """

    sigma_mm: float = 0.01
    rng: np.random.Generator = field(default_factory=np.random.default_rng)

    def __post_init__(self) -> None:
        if not np.isfinite(self.sigma_mm) or self.sigma_mm < 0:
            raise ValueError(f"tracker noise must be a non-negative number of mm, got {self.sigma_mm}")

    def measure(self, points_mm: np.ndarray) -> np.ndarray:
        """Noisy copies of true target centres (..., 3) in the base frame, mm."""
        points_mm = np.asarray(points_mm, dtype=float)
        if self.sigma_mm == 0:
            return points_mm.copy()
        return points_mm + self.rng.normal(0.0, self.sigma_mm, points_mm.shape)
