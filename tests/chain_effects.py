"""An independent simulator of the Delta's campaigns with effects, for the folder-machine diagnosis: the
closed-form kinematics of tests/chain_references.py (not pmcal's twin), the effects written here in their
own physical form, then tracker noise.

Effects: ``backlash`` (full dead band per motor, deg: the joint lags half of it against the last move),
``drift`` (per motor, deg/h, about the campaign's middle), ``frame`` (the base moving rigidly: v mm/h, w
deg/h about the world origin), ``alpha`` (uniform thermal expansion, 1/K: every length of the machine
scaled), and two out of every family's shape: ``sag`` (the platform sinks by ``sag`` mm times its squared
distance from the axis over 250 mm squared: a structure bending under its own weight) and ``harmonic`` (a
second-harmonic gear error, deg, ``sin(2 theta)`` per motor).
"""

from __future__ import annotations

import numpy as np

from tests.chain_references import DELTA, delta_fk, delta_ik

BOX = ([-250.0, -250.0, -950.0], [250.0, 250.0, -650.0])
MOTOR_RANGE = (-35.0, 80.0)


def last_move(commands: np.ndarray) -> np.ndarray:
    """+1 / -1 per motor: the sign of its last move in row order (0 before it first moves)."""
    out = np.zeros_like(commands)
    for i in range(1, len(commands)):
        d = commands[i] - commands[i - 1]
        out[i] = np.where(np.abs(d) > 1e-9, np.sign(d), out[i - 1])
    return out


def delta_campaign(n: int, rng: np.random.Generator, *, backlash=(0.0, 0.0, 0.0), drift=(0.0, 0.0, 0.0),
                   frame=None, alpha: float = 0.0, sag: float = 0.0, harmonic: float = 0.0, sigma: float = 0.01,
                   seconds_per_pose: float = 120.0):
    """(commands (n, 3) deg, nests (n, 3, 3) mm, time_s (n,), temp_c (n,)): ``n`` poses drawn uniformly in
    the workspace box and driven in that order, 2 minutes apart, temperature rising 6 K and falling back."""
    cmd = []
    while len(cmd) < n:
        th = delta_ik(rng.uniform(*BOX)[None])[0]
        if np.isfinite(th).all() and np.all((th > MOTOR_RANGE[0]) & (th < MOTOR_RANGE[1])):
            cmd.append(th)
    cmd = np.array(cmd)
    time_s = np.arange(n) * seconds_per_pose
    hours = (time_s - time_s.mean()) / 3600.0
    temp = 20.0 + 6.0 * np.sin(np.pi * np.arange(n) / n)
    joints = (cmd - 0.5 * np.asarray(backlash) * last_move(cmd) + np.asarray(drift) * hours[:, None]
              + harmonic * np.sin(np.deg2rad(2.0 * cmd)))
    nests = np.empty((n, 3, 3))
    for i in range(n):
        grow = 1.0 + alpha * (temp[i] - temp.mean())
        dims = dict(DELTA, **{k: DELTA[k] * grow for k in ("Rb", "La", "Lf", "Rp")})
        nests[i] = delta_fk(joints[i:i + 1], dims)[0] + np.asarray(DELTA["nests"]) * grow
    if sag:
        nests[..., 2] -= sag * (nests[..., 0] ** 2 + nests[..., 1] ** 2) / 250.0 ** 2
    if frame is not None:
        v, w = np.asarray(frame[:3], float), np.deg2rad(np.asarray(frame[3:], float))
        nests = nests + (v + np.cross(w, nests)) * hours[:, None, None]
    return cmd, nests + rng.normal(0.0, sigma, nests.shape), time_s, temp
