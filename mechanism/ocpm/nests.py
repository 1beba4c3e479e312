"""Target nests: where the reflectors really sit on the platform, and the gauge of their offsets.

The platform frame is defined by the targets (docs/ocpm_2dof.md, docs/tracker_frame.md: the rigid fit of the measured targets to their
drawing coordinates X). A common translation or rotation of all nests therefore moves the platform frame
itself: it is the same machine as a platform geometry error (``SS.dc*``, ``L*.da*``, ``L*.dmu/dnu``) and
no measurement can tell the two apart. So nest offsets are written in the *shape* subspace: the offsets
that leave the rigid fit of (X + offsets) to X at the identity (3 k - 6 coordinates, 3 for three nests:
the changes of the triangle's side lengths). See docs/tracker_frame.md. Units: mm, platform frame.
"""

from __future__ import annotations

import numpy as np


def rigid_modes(X: np.ndarray) -> np.ndarray:
    """(3 k, 6) the small rigid motions of the points X (k, 3): three translations, three rotations."""
    X = np.asarray(X, float)
    k = len(X)
    Xc = X - X.mean(axis=0)
    G = np.zeros((k, 3, 6))
    G[:, :, :3] = np.eye(3)
    for a in range(3):
        e = np.eye(3)[a]
        G[:, :, 3 + a] = np.cross(e, Xc)
    return G.reshape(3 * k, 6)


def shape_basis(X: np.ndarray) -> np.ndarray:
    """(3 k, 3 k - 6) orthonormal basis of nest offsets with no rigid part (columns)."""
    G = rigid_modes(X)
    U, _, _ = np.linalg.svd(G, full_matrices=True)
    return U[:, 6:]


def shape_part(offsets: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Offsets (k, 3) with their rigid part removed (orthogonal projection onto :func:`shape_basis`)."""
    N = shape_basis(X)
    return (N @ (N.T @ np.asarray(offsets, float).reshape(-1))).reshape(-1, 3)
