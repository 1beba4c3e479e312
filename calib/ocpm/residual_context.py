"""What an unexplained residual correlates with: time, temperature, motor angles, tilt, approach, payload.

When no family of the vocabulary explains the structure left, the engineer needs to know where to look.
For every context variable z available in the campaign each pose's residual (its k targets x 3
coordinates, mm, base frame) is regressed on (1, z) and, for the periodic motor angles, on
(1, sin, cos): the share of the residual's sum of squares it explains across all coordinates and the F
test of that share against the rest (per pose, so one noisy pose does not count nine times).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from pmcal.mechanism.ocpm.data import Measurements


@dataclass
class ContextLink:
    """How strongly the residual follows one context variable."""

    context: str
    share: float          # fraction of the residual sum of squares explained (0..1)
    p_value: float        # F test, per pose
    direction: str        # the coordinate that follows it most (e.g. "t2_z")


def contexts(meas: Measurements) -> dict[str, np.ndarray]:
    """Context regressors (N, q) of a campaign: row order, time, temperature, payload, motor angles
    (sin, cos), tilt (from the measured targets' plane), approach per motor."""
    n = len(meas)
    out = {"row order": np.arange(n, dtype=float)[:, None]}
    if meas.time_s is not None and np.all(np.isfinite(meas.time_s)):
        out["time"] = np.asarray(meas.time_s, float)[:, None]
    if meas.temp_c is not None and np.all(np.isfinite(meas.temp_c)):
        out["temperature"] = np.asarray(meas.temp_c, float)[:, None]
    if meas.payload_kg is not None and np.ptp(meas.payload_kg) > 0:
        out["payload"] = np.asarray(meas.payload_kg, float)[:, None]
    for j in range(2):
        th = np.deg2rad(meas.m_cmd_deg[:, j])
        out[f"motor {j + 1} angle"] = np.stack([np.sin(th), np.cos(th)], axis=1)
    if meas.targets.shape[1] >= 3 and np.all(np.isfinite(meas.targets[:, :3])):
        t = meas.targets[:, :3]
        nrm = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        out["tilt"] = np.arccos(np.clip(np.abs(nrm[:, 2]) / np.linalg.norm(nrm, axis=1), -1, 1))[:, None]
    if meas.approach is not None:
        for j in range(2):
            if np.ptp(meas.approach[:, j]) > 0:
                out[f"motor {j + 1} approach"] = np.asarray(meas.approach[:, j], float)[:, None]
    return out


def characterise(meas: Measurements, resid_mm: np.ndarray, top: int = 3) -> list[ContextLink]:
    """The context variables the residual (N, k, 3) mm follows, strongest first (``top`` of them)."""
    n = len(meas)
    Y = np.nan_to_num(resid_mm.reshape(n, -1))
    Y = Y - Y.mean(axis=0)
    tot = float(np.sum(Y**2))
    names = [f"t{i // 3 + 1}_{'xyz'[i % 3]}" for i in range(Y.shape[1])]
    links = []
    for name, Z in contexts(meas).items():
        X = np.column_stack([np.ones(n), Z - Z.mean(axis=0)])
        coef, *_ = np.linalg.lstsq(X, Y, rcond=None)
        fit = X @ coef
        ss = np.sum(fit**2, axis=0)
        share = float(ss.sum() / tot) if tot > 0 else 0.0
        q = Z.shape[1]
        if n - q - 1 <= 0 or share >= 1:
            p = 0.0
        else:
            F = (share / q) / ((1 - share) / (n - q - 1))
            p = float(stats.f.sf(F, q, n - q - 1))
        links.append(ContextLink(name, share, p, names[int(np.argmax(ss))]))
    links.sort(key=lambda c: c.p_value)
    return links[:top]


def describe(links: list[ContextLink]) -> str:
    """One line for the notes."""
    if not links:
        return "the residual left follows none of the recorded context"
    parts = [f"{c.context} ({100 * c.share:.0f} % of it, p = {c.p_value:.2g}, mostly {c.direction})" for c in links]
    return "the structure left follows: " + "; ".join(parts)
