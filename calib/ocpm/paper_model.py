"""The paper's error model of the over-constrained PM (paper 000 eq. 12-14) and its linearised
pose-error model (eq. 18-20), as :class:`pmcal.calib.solvers.problem.Problem` objects.

Per-limb model (eq. 14). At every measured pose (r, R) (rigid fit of the tracker targets) the real
inverse kinematics of actuated limb j with candidate errors gives the joint angle ``beta_j``; the machine
was commanded ``m_j`` and its joint sits at ``m_j + dtheta_j``. The residual is

    e_j = beta_j(r, R; errors) - (m_j + dtheta_j)          [rad]

11 parameters a limb (paper Table 1/2, :data:`PAPER_LIMB_FIELDS`). Optionally (``planarity=True``) a
second residual per limb and pose: the distance of S_j from the plane of the platform revolute at A_j
[mm], the closure condition the paper's distance-only model drops. It is the only place where the
platform-axis tilts ``dmu``/``dnu`` appear and it adds one equation per limb and pose.

Noise. The residuals inherit the tracker noise through the measured pose. For each pose the residual
block is mapped to the target coordinates by central differences (the Jacobian ``G_i``), its covariance
is ``sigma^2 G_i G_i^T`` and the model whitens each pose block with the inverse Cholesky factor, so the
problem's residuals are independent with unit variance (``Problem.sigma = 1``) and the chi-square of a
correct fit is about the number of residuals minus parameters. ``weighting="none"`` is the paper's
unweighted sum of squared motor-angle errors (rad), with ``sigma`` the RMS of the per-entry noise.

Linearised pose-error model (eq. 18-20): ``dX = H eps`` with ``dX`` the measured minus nominally
predicted orientation (pointing coordinates ``theta (cos phi, sin phi)``, rad) and
``H = -J_p^{-1} E`` from the nominal motor Jacobian ``J_p = d beta / d p`` and the error coefficient
matrix ``E = d(beta - dtheta) / d eps`` at the nominal pose (eq. 7 position). See docs/identification.md.

Units: mm and rad inside; frames as in docs/formats.md §1.

At ~400 lines: the eq. 14 model, its Jacobians and the linearised pose model share the per-limb
vector layout; the procedure that uses them is :mod:`pmcal.calib.ocpm.paper_calibration`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pmcal.mechanism.ocpm.config import Geometry, default_geometry
from pmcal.mechanism.ocpm.kinematics import from_pointing_coords, limb_ik, nominal_fk, nominal_pose
from pmcal.mechanism.ocpm.params import ANGULAR_FIELDS, PAPER_LIMB_FIELDS, ErrorSet, describe
from pmcal.mechanism.rigid import fit_pose
from pmcal.mechanism.rotations import tilt_torsion_angles
from pmcal.calib.solvers.problem import Problem, box_problem

TILT_FIELDS: tuple[str, ...] = ("dmu", "dnu")
#: Default search box half-widths (mm, rad): wider than the paper's Table 2 errors (max 2 mm, 0.4 deg).
BOX_MM = 3.0
BOX_RAD = float(np.deg2rad(0.5))
#: Target-coordinate step for the noise propagation (mm).
_H_TARGET = 1e-3


def param_names(limbs: tuple[int, ...] = (1, 2), tilts: bool = False) -> list[str]:
    """Parameter keys of the per-limb model: the paper's 11 a limb (+ ``dmu``, ``dnu`` if ``tilts``)."""
    fields = PAPER_LIMB_FIELDS + (TILT_FIELDS if tilts else ())
    return [f"L{j}.{f}" for j in limbs for f in fields]


def param_units(names: list[str]) -> list[str]:
    """``"rad"`` for angular keys, ``"mm"`` otherwise (internal units)."""
    return ["rad" if k.split(".", 1)[1] in ANGULAR_FIELDS else "mm" for k in names]


def default_half_width(names: list[str], mm: float = BOX_MM, rad: float = BOX_RAD) -> np.ndarray:
    """Search box half-width per parameter (mm or rad)."""
    return np.array([rad if u == "rad" else mm for u in param_units(names)])


def explain(key: str, geom: Geometry | None = None) -> str:
    """Plain words for a parameter of this model, and why the motor-angle equation may not see it."""
    geom = geom or default_geometry()
    words = describe(key)
    group, name = key.split(".", 1)
    if name in TILT_FIELDS:
        return (f"{words}: limb {group[1:]}'s motor angle does not depend on it (only the planarity "
                "condition does)")
    if group.startswith("L") and name in ("dax", "day"):
        psi = geom.psi[int(group[1:]) - 1]
        axis = (-np.sin(psi), np.cos(psi))[0 if name == "dax" else 1]
        if abs(abs(axis) - 1.0) < 1e-9:
            return (f"{words}, i.e. along its own platform revolute axis: S_{group[1:]} lies in the plane "
                    f"through A_{group[1:]} normal to that axis, so the link length S-A and the motor angle "
                    "do not change to first order")
    return words


_VEC = {"dbx": ("db", 0), "dby": ("db", 1), "dbz": ("db", 2), "dax": ("da", 0), "day": ("da", 1),
        "daz": ("da", 2)}
_FIELD_OF = {k: v[0] for k, v in _VEC.items()}


def errors_from_vector(names: list[str], X: np.ndarray, base: ErrorSet | None = None) -> ErrorSet:
    """An :class:`ErrorSet` with leading population dims ``X.shape[:-1]`` from vectors ``X (..., n)``.

    ``X`` in internal units (mm, rad) for the keys ``names``; every other parameter comes from ``base``
    (default nominal).
    """
    X = np.asarray(X, float)
    batch = X.shape[:-1]
    base = base or ErrorSet()
    touched = {_FIELD_OF.get(k.split(".", 1)[1], k.split(".", 1)[1]) for k in names if not k.startswith("SS.")}
    touched |= {"ss_dh" if k == "SS.dh" else "ss_dc" for k in names if k.startswith("SS.")}
    # untouched fields are read-only broadcast views (no copy): the population axis costs nothing there
    arrays = {k: (np.array if k in touched else np.asarray)(
        np.broadcast_to(np.asarray(getattr(base, k), float), batch + np.shape(getattr(base, k))))
        for k in ErrorSet.__dataclass_fields__}
    for col, key in enumerate(names):
        group, name = key.split(".", 1)
        if group == "SS":
            if name == "dh":
                arrays["ss_dh"] = X[..., col].copy()
            else:
                arrays["ss_dc"][..., "xyz".index(name[-1])] = X[..., col]
            continue
        j = int(group[1:]) - 1
        if name in _VEC:
            arr, k = _VEC[name]
            arrays[arr][..., j, k] = X[..., col]
        else:
            arrays[name][..., j] = X[..., col]
    return ErrorSet(**arrays)


def target_jacobian(fn, Y: np.ndarray, h: float = _H_TARGET) -> np.ndarray:
    """Per-pose derivative of ``fn(Y (N, k, 3)) -> (N, C)`` w.r.t. that pose's target coordinates.

    Returns (N, C, 3k), central differences (all poses perturbed at once: poses are independent).
    """
    N, k, _ = Y.shape
    cols = []
    for c in range(3 * k):
        d = np.zeros_like(Y)
        d[:, c // 3, c % 3] = h
        cols.append((fn(Y + d) - fn(Y - d)) / (2 * h))
    return np.stack(cols, axis=-1)


def whitening(G: np.ndarray, sigma_mm: float) -> np.ndarray:
    """Whitening matrices (N, C, C) for residual blocks with covariance ``sigma^2 G G^T``."""
    C = sigma_mm**2 * np.einsum("nca,nda->ncd", G, G)
    L = np.linalg.cholesky(C)
    return np.linalg.inv(L)


@dataclass
class PaperModel:
    """Paper eq. 14 at measured poses: residuals of the actuated limbs for candidate parameter vectors.

    targets : (N, k, 3) measured tracker targets, base frame, mm.
    m_cmd : (N, 2) commanded motor angles, rad.
    names : parameter keys identified (internal units in vectors); others come from ``base``.
    limbs : actuated limbs modelled (subset of (1, 2)).
    planarity : add the platform-revolute plane condition as a second residual per limb and pose.
    weighting : ``"noise"`` (whiten by the propagated tracker noise) or ``"none"`` (paper eq. 14).
    sigma_mm : tracker noise per coordinate, mm.
    """

    targets: np.ndarray
    m_cmd: np.ndarray
    names: list[str]
    limbs: tuple[int, ...] = (1, 2)
    planarity: bool = False
    weighting: str = "noise"
    sigma_mm: float = 0.01
    geom: Geometry = field(default_factory=default_geometry)
    base: ErrorSet = field(default_factory=ErrorSet)

    def __post_init__(self) -> None:
        if self.weighting not in ("noise", "none"):
            raise ValueError(f"weighting must be 'noise' or 'none', got {self.weighting!r}")
        if self.planarity and self.weighting != "noise":
            raise ValueError("the planarity residual (mm) mixes units with the motor angles (rad): "
                             "it needs weighting='noise'")
        self.targets = np.asarray(self.targets, float)
        self.m_cmd = np.asarray(self.m_cmd, float)
        self.X = self.geom.targets[: self.targets.shape[1]]
        self.r, self.R, self.fit_rms = fit_pose(self.targets, self.X)
        self._cmd = self.m_cmd[:, np.asarray(self.limbs) - 1]
        G = target_jacobian(self._raw_at_targets, self.targets)       # at the nominal parameters
        self.noise_std = self.sigma_mm * np.sqrt(np.einsum("nca,nca->nc", G, G))   # (N, C) raw units
        if self.weighting == "noise":
            self.W = whitening(G, self.sigma_mm)
            self.sigma = 1.0
        else:
            self.W = None
            self.sigma = float(np.sqrt(np.mean(self.noise_std**2)))

    # ------------------------------------------------------------------ residuals
    @property
    def n_components(self) -> int:
        """Residual entries per pose."""
        return len(self.limbs) * (2 if self.planarity else 1)

    def raw(self, X: np.ndarray, r: np.ndarray | None = None, R: np.ndarray | None = None) -> np.ndarray:
        """Unweighted residuals (..., N, C): motor-angle errors (rad) per limb, then planarity (mm).

        ``X`` (..., n) parameter vectors; ``r``, ``R`` poses (default: the measured ones).
        """
        X = np.asarray(X, float)
        errors = errors_from_vector(self.names, X, self.base)
        ik = limb_ik(self.r if r is None else r, self.R if R is None else R, errors, self.geom, self.limbs)
        dtheta = np.asarray(errors.dtheta)[..., np.asarray(self.limbs) - 1]
        e = ik.beta - (self._cmd + dtheta[..., None, :])
        return np.concatenate([e, ik.planarity], axis=-1) if self.planarity else e

    def _raw_at_targets(self, Y: np.ndarray) -> np.ndarray:
        r, R, _ = fit_pose(Y, self.X)
        return self.raw(np.zeros(len(self.names)), r, R)

    def residuals(self, X: np.ndarray) -> np.ndarray:
        """Problem residuals (..., N*C): whitened (unit variance) or raw rad, pose-major."""
        e = self.raw(X)
        if self.W is not None:
            e = np.einsum("ncd,...nd->...nc", self.W, e)
        return e.reshape(e.shape[:-2] + (-1,))

    def motor_residual(self, x: np.ndarray) -> np.ndarray:
        """(N, len(limbs)) motor-angle residuals (rad) at one parameter vector."""
        return self.raw(x)[..., : len(self.limbs)]

    def orientations(self) -> tuple[np.ndarray, np.ndarray]:
        """Measured tilt-torsion angles (phi, theta) of the poses, rad (paper eq. 17)."""
        return tilt_torsion_angles(self.R)

    def design(self) -> "PaperModel":
        """The same model on the nominal machine at the measured orientations, noise-free: where
        first-order identifiability is judged (see :class:`pmcal.calib.solvers.problem.Problem`)."""
        return nominal_design(*self.orientations(), self.geom, names=self.names, limbs=self.limbs,
                              planarity=self.planarity, weighting=self.weighting, sigma_mm=self.sigma_mm)

    def problem(self, half_width: np.ndarray | None = None, x0: np.ndarray | None = None,
                with_design: bool = True) -> Problem:
        """This model as a :class:`Problem` (box ``x0 ± half_width``, default :func:`default_half_width`)."""
        hw = default_half_width(self.names) if half_width is None else np.asarray(half_width, float)
        unit = "sigma" if self.W is not None else "rad"
        design = self.design().problem(hw, x0, with_design=False) if with_design else None
        return box_problem(self.residuals, self.names, param_units(self.names), hw, x0=x0,
                           sigma=self.sigma, design=design,
                           info={"model": "paper", "residual_unit": unit, "n_poses": len(self.r),
                                 "limbs": self.limbs})


def from_measurements(meas, limbs: tuple[int, ...] = (1, 2), tilts: bool = False, planarity: bool = False,
                      weighting: str = "noise", sigma_mm: float | None = None,
                      geom: Geometry | None = None) -> PaperModel:
    """A :class:`PaperModel` for a :class:`pmcal.mechanism.ocpm.data.Measurements` campaign."""
    geom = geom or default_geometry()
    return PaperModel(targets=meas.targets, m_cmd=np.deg2rad(meas.m_cmd_deg),
                      names=param_names(limbs, tilts), limbs=tuple(limbs), planarity=planarity,
                      weighting=weighting, sigma_mm=geom.sigma_mm if sigma_mm is None else sigma_mm,
                      geom=geom)


def nominal_design(phi: np.ndarray, theta: np.ndarray, geom: Geometry | None = None,
                   **kwargs) -> PaperModel:
    """The model at noise-free nominal poses (phi, theta rad) commanded by the nominal IK.

    The design matrix for identifiability studies and pose selection (no measurement needed).
    """
    geom = geom or default_geometry()
    r, R = nominal_pose(phi, theta, geom)
    Y = r[:, None, :] + np.einsum("nij,kj->nki", R, geom.targets)
    m = limb_ik(r, R, None, geom, (1, 2)).beta
    limbs = kwargs.pop("limbs", (1, 2))
    names = kwargs.pop("names", None) or param_names(limbs, kwargs.pop("tilts", False))
    return PaperModel(targets=Y, m_cmd=m, names=names, limbs=limbs, geom=geom, **kwargs)


def design_blocks(phi: np.ndarray, theta: np.ndarray, names: list[str] | None = None,
                  limbs: tuple[int, ...] = (1, 2), geom: Geometry | None = None,
                  sigma_mm: float | None = None) -> np.ndarray:
    """Whitened Jacobian rows of every candidate pose, (N, C, n): the input of pose selection.

    Nominal machine at orientations (phi, theta) rad, commanded by the nominal IK.
    """
    geom = geom or default_geometry()
    d = nominal_design(phi, theta, geom, names=names, limbs=limbs,
                       sigma_mm=geom.sigma_mm if sigma_mm is None else sigma_mm)
    J = d.problem(with_design=False).jacobian(np.zeros(len(d.names)))
    return J.reshape(len(phi), d.n_components, len(d.names))


# ---------------------------------------------------------------------- linearised model (eq. 18-20)
def constraints(r: np.ndarray, R: np.ndarray, m_cmd: np.ndarray, errors: ErrorSet,
                geom: Geometry) -> np.ndarray:
    """The closed chain's constraint values (..., N, 7), mm, zero on a consistent machine at rest.

    Per pose: the actuated limbs' distance equations as motor-angle errors times the link length
    ``l (beta_j - m_j - dtheta_j)`` (j = 1, 2; actuation wrenches), the plane conditions of all four RSR
    limbs (constraint wrenches; a passive limb's angle solves its distance equation), and the SS limb
    length ``|r + R c| - (h + dh)``. Four RSR limbs and the SS limb give 7 equations for the 6 pose
    coordinates: one is redundant (the over-constraint).
    """
    ik = limb_ik(r, R, errors, geom, tuple(range(1, geom.n_limbs + 1)))
    dtheta = np.asarray(errors.dtheta)[..., None, :2]
    act = geom.l * (ik.beta[..., :2] - m_cmd - dtheta)
    c = r + np.einsum("nij,...j->...ni", R, np.asarray(errors.ss_dc, float))
    ss = np.linalg.norm(c, axis=-1) - (geom.h + np.asarray(errors.ss_dh, float)[..., None])
    return np.concatenate([act, ik.planarity, ss[..., None]], axis=-1)


def pose_vector(r: np.ndarray, R: np.ndarray, r0: np.ndarray, R0: np.ndarray) -> np.ndarray:
    """6-D pose difference (N, 6): ``(r - r0 [mm], rotation vector of R R0^T [rad], base frame)``."""
    from scipy.spatial.transform import Rotation

    w = Rotation.from_matrix(R @ np.swapaxes(R0, -1, -2)).as_rotvec()
    return np.concatenate([r - r0, w], axis=-1)


@dataclass
class LinearPoseModel:
    """Paper eq. 18-19 ``dX = H eps`` at measured poses, whitened by the propagated tracker noise.

    dX : (N, 6) measured minus nominal pose at the commanded motor angles (mm, rad; :func:`pose_vector`).
    H : (N, 6, n) first-order pose error per parameter, ``H = -(J_x^T J_x)^{-1} J_x^T E_e`` (eq. 18) with
        ``J_x`` (7 x 6) the derivative of the chain's :func:`constraints` w.r.t. the platform twist and
        ``E_e`` (7 x n) w.r.t. the parameters, at the nominal pose (paper eq. 7).
    W : (N, 6, 6) whitening of the measured pose.
    """

    dX: np.ndarray
    H: np.ndarray
    W: np.ndarray
    names: list[str]

    def residuals(self, X: np.ndarray) -> np.ndarray:
        """Whitened ``H x - dX`` for parameter vectors (..., n) -> (..., 6N)."""
        pred = np.einsum("nci,...i->...nc", self.H, np.asarray(X, float))
        e = np.einsum("ncd,...nd->...nc", self.W, pred - self.dX)
        return e.reshape(e.shape[:-2] + (-1,))

    def matrix(self) -> np.ndarray:
        """The whitened identification matrix (6N, n)."""
        return np.einsum("ncd,ndi->nci", self.W, self.H).reshape(-1, len(self.names))

    def problem(self, half_width: np.ndarray | None = None) -> Problem:
        hw = default_half_width(self.names) if half_width is None else np.asarray(half_width, float)
        A = self.matrix()
        return box_problem(self.residuals, self.names, param_units(self.names), hw, sigma=1.0,
                           jac=lambda x: A, info={"model": "linear_pose", "residual_unit": "sigma",
                                                  "n_poses": len(self.dX)})


def error_jacobian(r: np.ndarray, R: np.ndarray, m_cmd: np.ndarray, names: list[str], geom: Geometry,
                   h_pose: float = 1e-6) -> np.ndarray:
    """Paper eq. 18 error Jacobian ``J_e = -(J_x^T J_x)^{-1} J_x^T E_e`` (N, 6, n) at poses (r, R)."""
    from pmcal.mechanism.rotations import rot_x, rot_y, rot_z

    n = len(names)
    hx = 1e-4 * default_half_width(names)
    X = np.concatenate([np.diag(hx), -np.diag(hx)])
    C = constraints(r, R, m_cmd, errors_from_vector(names, X), geom)          # (2n, N, 7)
    E = np.moveaxis((C[:n] - C[n:]) / (2 * hx[:, None, None]), 0, -1)      # (N, 7, n)
    zero = ErrorSet()
    cols = []
    for k in range(6):
        dr = np.zeros(3)
        if k < 3:
            dr[k] = h_pose
            plus = constraints(r + dr, R, m_cmd, zero, geom)
            minus = constraints(r - dr, R, m_cmd, zero, geom)
        else:
            rot = (rot_x, rot_y, rot_z)[k - 3]
            plus = constraints(r, rot(h_pose) @ R, m_cmd, zero, geom)
            minus = constraints(r, rot(-h_pose) @ R, m_cmd, zero, geom)
        cols.append((plus - minus) / (2 * h_pose))
    Jx = np.stack(cols, axis=-1)                                               # (N, 7, 6)
    return -np.linalg.pinv(Jx) @ E


def pose_sensitivity(p: np.ndarray, names: list[str], geom: Geometry | None = None,
                     h_p: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """``J_p = d m / d p`` (N, 2, 2) and ``E = d m / d eps`` (N, 2, n) of the motor commands
    ``m = beta - dtheta`` at nominal poses with pointing coordinates ``p`` (N, 2) rad (eq. 7 position)."""
    geom = geom or default_geometry()
    n = len(names)
    hx = 1e-4 * default_half_width(names)

    def cmd(pp: np.ndarray, X: np.ndarray) -> np.ndarray:
        r, R = nominal_pose(*from_pointing_coords(pp), geom)
        e = errors_from_vector(names, X)
        return limb_ik(r, R, e, geom, (1, 2)).beta - np.asarray(e.dtheta)[..., None, :2]

    X = np.concatenate([np.diag(hx), -np.diag(hx)])
    M = cmd(p, X)                                                  # (2n, N, 2)
    E = np.moveaxis((M[:n] - M[n:]) / (2 * hx[:, None, None]), 0, -1)
    zero = np.zeros((1, n))
    Jp = np.stack([(cmd(p + d, zero)[0] - cmd(p - d, zero)[0]) / (2 * h_p) for d in np.eye(2) * h_p], -1)
    return Jp, E


def linear_pose_model(meas, names: list[str] | None = None, sigma_mm: float | None = None,
                      geom: Geometry | None = None) -> LinearPoseModel:
    """Paper eq. 18-19 for a measurement campaign (both actuated limbs, 22 parameters by default).

    The nominal pose of each row is the nominal forward kinematics of its commanded motor angles.
    """
    geom = geom or default_geometry()
    names = names or param_names((1, 2))
    sigma_mm = geom.sigma_mm if sigma_mm is None else sigma_mm
    X = geom.targets[: meas.targets.shape[1]]
    m = np.deg2rad(meas.m_cmd_deg)
    r0, R0 = nominal_pose(*nominal_fk(m, geom), geom)

    def measured(Y: np.ndarray) -> np.ndarray:
        r, R, _ = fit_pose(Y, X)
        return pose_vector(r, R, r0, R0)

    dX = measured(meas.targets)
    W = whitening(target_jacobian(measured, meas.targets), sigma_mm)
    return LinearPoseModel(dX=dX, H=error_jacobian(r0, R0, m, names, geom), W=W, names=list(names))
