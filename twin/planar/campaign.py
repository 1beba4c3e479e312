"""Virtual measurement campaigns on the planar twin: commanded positions, servo and scale noise, readings.

A campaign visits K positions in order. At each the servo holds the commanded angle plus its motion
error ξ (paper eq. 35); the twin closes the loops; the linear scale's reading head is reset after each
measurement, so each reading is the change of |O1 O2| since the previous position plus one scale error
(eq. 34). Units: mm and radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pmcal.mechanism.planar.kinematics import inverse
from pmcal.mechanism.planar.noise import Noise
from pmcal.errors import RunError
from pmcal.twin.planar.twin import PlanarPoses, PlanarTwin


@dataclass
class Campaign:
    """One or several chains of readings (rad, mm).

    theta_cmd : (S, K, 2) commanded motor angles (what the controller believes it sent).
    readings : (S, K-1) scale changes between adjacent positions, mm.
    poses : the twin's poses (S*K of them, row-major), noise-free geometry with the servo errors applied.
    """

    theta_cmd: np.ndarray
    readings: np.ndarray
    poses: PlanarPoses


def measure(twin: PlanarTwin, theta_cmd: np.ndarray, noise: Noise, rng: np.random.Generator) -> Campaign:
    """Measure chains of positions: ``theta_cmd`` (K, 2) or (S, K, 2) rad, S independent chains."""
    cmd = np.asarray(theta_cmd, dtype=float)
    cmd3 = cmd[None] if cmd.ndim == 2 else cmd
    S, K, _ = cmd3.shape
    motor = cmd3 + rng.normal(0.0, noise.servo, cmd3.shape)
    poses = twin.assemble(motor.reshape(S * K, 2))
    if not np.all(poses.converged):
        k = int(np.flatnonzero(~poses.converged)[0])
        raise RunError(f"the twin did not assemble at motor angles {np.rad2deg(poses.motor[k])} deg "
                       f"(closure gap {poses.gap[k]:.3g} m)")
    length = poses.scale.reshape(S, K)
    readings = np.diff(length, axis=1) + rng.normal(0.0, noise.scale, (S, K - 1))
    return Campaign(theta_cmd=cmd3, readings=readings, poses=poses)


def batch_measure(twin: PlanarTwin, noise: Noise, rng: np.random.Generator):
    """A ``measure(theta_cmd (S, K, 2), ids)`` callback for :func:`pmcal.calib.planar.calibration.calibrate_many`."""
    def run(theta_cmd: np.ndarray, ids: np.ndarray) -> np.ndarray:
        return measure(twin, theta_cmd, noise, rng).readings
    return run


def commands_for(twin: PlanarTwin, r: np.ndarray, comp: np.ndarray | None = None) -> np.ndarray:
    """Motor commands (K, 2) rad that the controller sends for nominal positions ``r`` (K, 2) mm, with
    zero-offset compensation ``comp`` (rad) if given."""
    theta = inverse(twin.machine.geometry, r)
    if not np.all(np.isfinite(theta)):
        raise ValueError("a position is out of the nominal robot's reach")
    return theta - (np.zeros(2) if comp is None else comp)

