"""How far a correction table may put the true machine from a target beyond the exact identified inverse
kinematics: the interpolation bound of tests/test_delta_table_chain.py and tests/test_chain_loop.py.

For a table of corrections c = IK_identified - IK_nominal (per motor, deg) over the task coordinates, at a
target t inside the grid:
  e(t) <= e_direct(t) + |J| * e_interp(t)
- e_direct: the exact identified inverse kinematics' own error on the true machine;
- e_interp: the multilinear interpolation bound of the correction field, sum over axes of
  h_a^2 / 8 * |d2c/dx_a^2| (h_a the node spacing, the second derivative by central differences over
  +-h_a/2 at t, times 2 for its variation over the cell), as a vector norm over the motors (deg);
- |J|: the 2-norm of d task / d commands of the true machine at the commands driven (mm/deg, central
  differences).
"""

from __future__ import annotations

import numpy as np


def interpolation_bound_mm(twin, params: dict, truth: dict, table, task: np.ndarray,
                           commands: np.ndarray) -> np.ndarray:
    """|J| * e_interp (n,) mm at targets ``task`` (n, A) (the task coordinates are the table's axes, in
    their order) driven by ``commands`` (n, M) deg on the machine with errors ``truth``; ``params`` the
    identified errors the table was made of. A table of absolute commands (no reference) tabulates the
    identified IK itself: its bound, with c = IK_identified."""
    lo = np.array([a.min for a in table.axes])
    hi = np.array([a.max for a in table.axes])
    h = (hi - lo) / (np.array(table.shape) - 1)
    n_axes, n_motors = table.n_axes, table.n_motors

    def correction(x):
        return twin.inverse(x, params) - (0.0 if table.reference is None else twin.inverse(x, None))

    c0 = correction(task)
    curv = np.zeros((len(task), n_motors))
    for a in range(n_axes):
        d = np.zeros(n_axes)
        d[a] = h[a] / 2
        second = (correction(task + d) - 2 * c0 + correction(task - d)) / (h[a] / 2) ** 2
        curv += 2.0 * h[a] ** 2 / 8.0 * np.abs(second)
    e_interp = np.linalg.norm(curv, axis=1)                 # deg
    jac = np.zeros((len(task), n_axes, n_motors))
    for k in range(n_motors):
        dm = np.zeros(n_motors)
        dm[k] = 1e-3
        jac[:, :, k] = (twin.forward(commands + dm, truth) - twin.forward(commands - dm, truth)) / 2e-3
    return np.linalg.norm(jac, ord=2, axis=(1, 2)) * e_interp     # mm
