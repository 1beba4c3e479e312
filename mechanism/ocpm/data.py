"""A measurement campaign of the over-constrained PM as arrays (mm, degrees as named)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pmcal.mechanism.ocpm.config import Geometry, default_geometry
from pmcal.mechanism.rigid import fit_pose


@dataclass
class Measurements:
    """One row per measured pose, in measurement order (order carries the motion history).

    pose_id : labels; m_cmd_deg : (N, 2) commanded motor angles, deg; targets : (N, k, 3) measured
    target centres in the base frame, mm. Optional context (NaN/0 when absent): temp_c, time_s,
    payload_kg; approach : (N, 2) sign of the last motion into each pose per motor (0 unknown).
    """

    pose_id: list[str]
    m_cmd_deg: np.ndarray
    targets: np.ndarray
    temp_c: np.ndarray | None = None
    time_s: np.ndarray | None = None
    payload_kg: np.ndarray | None = None
    approach: np.ndarray | None = None
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.pose_id)

    def subset(self, idx) -> "Measurements":
        idx = np.asarray(idx)
        pick = lambda a: None if a is None else np.asarray(a)[idx]  # noqa: E731
        return Measurements(pose_id=[self.pose_id[i] for i in np.arange(len(self))[idx]],
                            m_cmd_deg=self.m_cmd_deg[idx], targets=self.targets[idx],
                            temp_c=pick(self.temp_c), time_s=pick(self.time_s),
                            payload_kg=pick(self.payload_kg), approach=pick(self.approach),
                            extra={k: v[idx] for k, v in self.extra.items()})

    def poses(self, geom: Geometry | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Measured platform poses by rigid fit: r (N, 3) mm, R (N, 3, 3), fit rms (N,) mm."""
        geom = geom or default_geometry()
        return fit_pose(self.targets, geom.targets[: self.targets.shape[1]])
