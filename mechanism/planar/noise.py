"""Measurement noise of the paper's simulation (section 6.1, eq. 34-35).

Both are Gaussian with zero mean; the paper's maximum errors are read as 3-sigma bounds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def scale_sigma(range_mm: float = 350.0, base_um: float = 3.0) -> float:
    """Standard deviation (mm) of one linear-scale reading (eq. 34).

    The scale's maximum error is ``±(3 + l0/1000) µm`` for a measuring range ``l0`` in mm; the reading
    head is reset after each measurement, so each reading of a change carries one such error:
    ``σ_m = (3 + l0/1000) · 1e-3 / 3`` mm (1.117 µm for l0 = 350 mm).
    """
    return (base_um + range_mm / 1000.0) * 1e-3 / 3.0


def servo_sigma(pulses_per_rev: float = 1e4, max_pulse_error: float = 4.0, reduction: float = 20.0) -> float:
    """Standard deviation (rad) of the active-link angle error at one position (eq. 35).

    ``ξ = (1/3) · (max_pulse_error / pulses_per_rev) · (1/reduction) · 360°`` = 0.0024° for the paper's
    servo (10^4 pulses/rev, 4 pulses maximum error, reduction 20).
    """
    return float(np.deg2rad(max_pulse_error / pulses_per_rev / reduction * 360.0 / 3.0))


@dataclass(frozen=True)
class Noise:
    """Noise of one campaign: scale reading ``scale`` (mm) and servo angle ``servo`` (rad), 1 sigma."""

    scale: float = scale_sigma()
    servo: float = servo_sigma()

    def scaled(self, factor: float) -> "Noise":
        return Noise(self.scale * factor, self.servo * factor)
