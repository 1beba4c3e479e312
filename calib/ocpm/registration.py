"""Frame registration: the pose of the machine's base frame in a laser tracker's own frame.

A tracker reports a base-frame point p at ``y = R p + t`` (``R`` (3, 3), ``t`` (3,) mm: the base frame's
pose in the tracker frame). The base frame is the machine's, defined by its motor axes
(docs/tracker_frame.md): origin O at the SS limb's base joint, y along motor 1's axis, z normal to both
motor axes. Rotating the base frame is the same machine as rotating every base-side parameter together,
so in the tracker frame these three base-side angles are held at zero (the gauge) and the registration
takes the rotation.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

#: Base-side parameters held at zero when the registration is identified: they fix the base frame to
#: the motor axes (L1.dalpha, L1.dgamma: motor 1 along y; L2.dalpha: motor 2 in the xy plane).
GAUGE_KEYS = ("L1.dalpha", "L1.dgamma", "L2.dalpha")


def rigid_fit(Y: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid transform ``Y ≈ R P + t`` of matched point sets (n, 3) mm (Kabsch, via scipy).

    Rows with a non-finite coordinate in either set are left out."""
    Y, P = np.asarray(Y, float).reshape(-1, 3), np.asarray(P, float).reshape(-1, 3)
    ok = np.isfinite(Y).all(axis=1) & np.isfinite(P).all(axis=1)
    if ok.sum() < 3:
        raise ValueError("need at least three matched points for a rigid fit")
    Y, P = Y[ok], P[ok]
    yc, pc = Y.mean(axis=0), P.mean(axis=0)
    rot, _ = Rotation.align_vectors(Y - yc, P - pc)
    R = rot.as_matrix()
    return R, yc - R @ pc


def apply(R: np.ndarray, t: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Base-frame points (..., 3) mm in the tracker frame."""
    return np.asarray(points, float) @ np.asarray(R).T + np.asarray(t)


def inverse(R: np.ndarray, t: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Tracker-frame points (..., 3) mm in the base frame."""
    return (np.asarray(points, float) - np.asarray(t)) @ np.asarray(R)


def rotation_error_deg(R_est: np.ndarray, R_true: np.ndarray) -> float:
    """Angle of the rotation between two registrations, deg."""
    return float(np.rad2deg(Rotation.from_matrix(R_est @ R_true.T).magnitude()))


def read_registration(doc: dict) -> tuple[np.ndarray, np.ndarray]:
    """Registration from a JSON document ``{"R": 3x3, "t_mm": [x, y, z]}`` (the ``registration`` block
    of an identified params JSON has this form); raises ValueError naming the field."""
    try:
        R = np.asarray(doc["R"], float)
    except (KeyError, TypeError, ValueError):
        raise ValueError("field 'R' must be a 3x3 list of numbers") from None
    try:
        t = np.asarray(doc["t_mm"], float)
    except (KeyError, TypeError, ValueError):
        raise ValueError("field 't_mm' must be a list of three numbers (mm)") from None
    if R.shape != (3, 3) or not np.isfinite(R).all():
        raise ValueError("field 'R' must be a 3x3 list of numbers")
    if t.shape != (3,) or not np.isfinite(t).all():
        raise ValueError("field 't_mm' must be a list of three numbers (mm)")
    if abs(np.linalg.det(R) - 1) > 1e-3 or np.abs(R.T @ R - np.eye(3)).max() > 1e-3:
        raise ValueError("field 'R' is not a rotation matrix (orthonormal, det +1)")
    return Rotation.from_matrix(R).as_matrix(), t


def motor_axes_frame(errors, geom) -> np.ndarray:
    """The machine's base frame as the motor axes define it, in the frame its ``errors`` are given in.

    Columns x, y, z (3, 3): y along motor 1's axis, z along motor 1's axis x motor 2's axis (normal to
    both), x = y x z; the origin (the SS joint) is common. It is the identity when ``L1.dalpha``,
    ``L1.dgamma`` and ``L2.dalpha`` are zero, and otherwise what a tracker-frame calibration calls the
    base frame: an orientation ``R`` in that frame is ``Q R`` in the errors' frame, and the true
    registration of a tracker at pose ``(R_t, t_t)`` of the errors' frame is ``(R_t Q, t_t)``.

    errors : :class:`pmcal.mechanism.ocpm.params.ErrorSet`; geom : the machine's geometry.
    """
    from pmcal.mechanism.ocpm.kinematics import limb_frames

    a = [limb_frames(geom.psi[j], errors.dalpha[j], errors.dgamma[j])[:, 1] for j in range(2)]
    z = np.cross(a[0], a[1])
    z /= np.linalg.norm(z)
    y = a[0] / np.linalg.norm(a[0])
    return np.column_stack([np.cross(y, z), y, z])


#: Keys of a small rigid correction of the base frame (rotation vector, rad; translation, mm) that
#: :class:`FrameCorrected` adds to a forward model.
FRAME_KEYS = ("frame.rx", "frame.ry", "frame.rz", "frame.tx", "frame.ty", "frame.tz")


class FrameCorrected:
    """A :class:`~pmcal.calib.ocpm.forward_model.ForwardModel` whose targets are carried by a small rigid
    correction of the base frame, ``y = dR(r) T + dt`` with the keys :data:`FRAME_KEYS`: the
    registration's residual uncertainty as parameters of a fit (e.g. the diagnosis baseline after a
    registration, so that an effect the registration partly absorbed is fitted with the frame, not
    against it). Every other key, method and attribute is the wrapped model's. Derivatives of the
    rotation keys are taken at the current correction (exact to first order in its size, ~1e-4 rad)."""

    def __init__(self, inner):
        self.inner = inner
        self.geom = inner.geom
        self.v = np.zeros(6)

    def __getattr__(self, name):
        return getattr(self.inner, name)

    @property
    def stiffness_ratio(self) -> float:
        return self.inner.stiffness_ratio

    def set(self, errors, stiffness_ratio: float | None = None) -> None:
        self.v = np.zeros(6)
        self.inner.set(errors, stiffness_ratio)

    def set_vector(self, keys: list[str], x: np.ndarray, ratio0: float) -> None:
        x = np.asarray(x, float)
        self.v = np.array([x[keys.index(k)] if k in keys else 0.0 for k in FRAME_KEYS])
        inner = [i for i, k in enumerate(keys) if k not in FRAME_KEYS]
        self.inner.set_vector([keys[i] for i in inner], x[inner], ratio0)

    def _carry(self, T, dT, keys):
        R = Rotation.from_rotvec(self.v[:3]).as_matrix()
        Y = T @ R.T + self.v[3:]
        if dT is None:
            return Y, None
        inner = [k for k in keys if k not in FRAME_KEYS]
        out = np.zeros(Y.shape + (len(keys),))
        E = np.eye(3)
        for c, k in enumerate(keys):
            if k in FRAME_KEYS:
                a = FRAME_KEYS.index(k)
                out[..., c] = np.cross(E[a], Y - self.v[3:]) if a < 3 else E[a - 3]
            else:
                out[..., c] = dT[..., inner.index(k)] @ R.T
        return Y, out

    def predict(self, m_cmd_deg, keys=None):
        inner = None if keys is None else [k for k in keys if k not in FRAME_KEYS]
        T, dT = self.inner.predict(m_cmd_deg, inner)
        return self._carry(T, dT, keys or [])

    def predict_meas(self, meas, keys, derivatives: bool = True):
        inner = [k for k in keys if k not in FRAME_KEYS]
        if derivatives:
            T, dT = self.inner.predict_meas(meas, inner)
        else:
            T, dT = self.inner.predict_meas(meas, inner, derivatives=False)
        return self._carry(T, dT, keys)

    def targets(self, meas):
        return self._carry(self.inner.targets(meas), None, [])[0]
