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
    target centres, mm, in the base frame (or in the tracker's own frame for a campaign identified with
    registration, see docs/tracker_frame.md). A blocked target is NaN in all three coordinates
    (:attr:`visible` is the mask); every row has at least two visible targets. Optional context (NaN/0 when absent): temp_c, time_s,
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

    @property
    def visible(self) -> np.ndarray:
        """(N, k) bool: targets measured in that row (False: blocked, all three coordinates NaN)."""
        return np.isfinite(self.targets).all(axis=-1)

    def subset(self, idx) -> "Measurements":
        idx = np.asarray(idx)
        pick = lambda a: None if a is None else np.asarray(a)[idx]  # noqa: E731
        return Measurements(pose_id=[self.pose_id[i] for i in np.arange(len(self))[idx]],
                            m_cmd_deg=self.m_cmd_deg[idx], targets=self.targets[idx],
                            temp_c=pick(self.temp_c), time_s=pick(self.time_s),
                            payload_kg=pick(self.payload_kg), approach=pick(self.approach),
                            extra={k: v[idx] for k, v in self.extra.items()})

    def poses(self, geom: Geometry | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Measured platform poses by rigid fit: r (N, 3) mm, R (N, 3, 3), fit rms (N,) mm.

        Rows with a blocked target are fitted to their visible targets (needs three; with two the pose
        is NaN: the rotation about the line through them is unknown)."""
        geom = geom or default_geometry()
        X = geom.targets[: self.targets.shape[1]]
        vis = self.visible
        if vis.all():
            return fit_pose(self.targets, X)
        n = len(self)
        r, R, rms = np.full((n, 3), np.nan), np.full((n, 3, 3), np.nan), np.full(n, np.nan)
        full = vis.all(axis=1)
        if full.any():
            r[full], R[full], rms[full] = fit_pose(self.targets[full], X)
        for i in np.flatnonzero(~full & (vis.sum(axis=1) >= 3)):
            r[i], R[i], rms[i] = fit_pose(self.targets[i, vis[i]], X[vis[i]])
        return r, R, rms
