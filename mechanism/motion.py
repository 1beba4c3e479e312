"""Motion history of a campaign's motor commands, from the order of its rows (any machine, any number of
motors). Units: those of the commands."""

from __future__ import annotations

import numpy as np


def approach_from_order(cmd_deg: np.ndarray) -> np.ndarray:
    """Approach signs (N, M) from the row order: the sign of each motor's last change of command (a row
    that does not move a motor keeps its previous sign; the first row, whose history is unknown, is 0).
    Rows must be in measurement (time) order, as docs/formats.md requires."""
    cmd = np.atleast_2d(np.asarray(cmd_deg, float))
    s = np.zeros_like(cmd)
    s[1:] = np.sign(np.diff(cmd, axis=0))
    for i in range(1, len(s)):
        s[i] = np.where(s[i] == 0, s[i - 1], s[i])
    return s
