"""The digital twin of the over-constrained PM: a "real" machine that reaches motor commands.

A :class:`Twin` is the nominal MJCF model plus a set of geometric errors (all four limbs and SS) and the
closure compliance. Driving it to motor commands solves the closed chain quasi-statically
(:mod:`pmcal.twin.ocpm.assembly`) from an initial guess given by the closed-form nominal kinematics, and reads the
platform pose and the tracker targets off the MuJoCo model.

Interface units: mm and degrees for commands; the returned :class:`TwinState` is in mm and radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from pmcal.mechanism.ocpm.config import Geometry, default_geometry
from pmcal.mechanism.ocpm.kinematics import (from_pointing_coords, limb_frames, limb_ik, nominal_fk,
                                             nominal_pose, pointing_coords)
from pmcal.mechanism.ocpm.params import ErrorSet
from pmcal.mechanism.rotations import rot_x, rot_y
from pmcal.twin.ocpm.assembly import AssemblyResult, BatchAssembler, Stiffness
from pmcal.twin.ocpm.model import MM, SCENE_XML, ModelIndex, apply_errors, build_model, load_model
from pmcal.twin.render import render_model_png


@dataclass
class TwinState:
    """Where the machine went (mm, rad), one row per commanded pose.

    r : (N, 3) platform frame origin (the target-defined C_E) in the base frame, mm.
    R : (N, 3, 3) platform orientation.
    targets : (N, k, 3) tracker target centres in the base frame, mm (noise-free).
    joint : (N, 2) true motor joint angles (commanded + zero offset + drive effects), rad.
    gaps : (N, 4, 3) closure gaps S1_j - S2_j, mm (zero on a consistent machine).
    converged : (N,) bool; iterations : (N,) int.
    """

    r: np.ndarray
    R: np.ndarray
    targets: np.ndarray
    joint: np.ndarray
    gaps: np.ndarray
    ss_axial: np.ndarray
    converged: np.ndarray
    iterations: np.ndarray
    qpos: np.ndarray

    @property
    def closure_residual(self) -> np.ndarray:
        """(N, 4) norm of each limb's closure gap, mm."""
        return np.linalg.norm(self.gaps, axis=-1)


class Twin:
    """A real over-constrained PM: nominal model + errors + closure compliance.

    Parameters
    ----------
    errors : ErrorSet or dict of interface keys (mm, deg); None is the nominal machine.
    geom : nominal geometry (default: the built-in machine.toml).
    stiffness_ratio : actuated-closure and SS stiffness over passive-closure stiffness (default from
        machine.toml, reference 1000).
    passive_stiffness : passive closure stiffness, N/mm (default from machine.toml).
    gravity : include the gravity load in the equilibrium (default False: a geometric twin).
    """

    def __init__(self, errors: ErrorSet | dict | None = None, geom: Geometry | None = None,
                 stiffness_ratio: float | None = None, passive_stiffness: float | None = None,
                 gravity: bool = False):
        self.geom = geom or default_geometry()
        if isinstance(errors, dict):
            errors = ErrorSet.from_dict(errors, self.geom.n_limbs, self.geom.actuated)
        self.errors = errors if errors is not None else ErrorSet()
        self.model, self.index = build_model(self.errors, self.geom)
        self._scratch = mujoco.MjData(self.model)
        ratio = self.geom.stiffness_ratio if stiffness_ratio is None else float(stiffness_ratio)
        k_p = (self.geom.passive_closure_stiffness if passive_stiffness is None else passive_stiffness) / MM
        self.passive_stiffness = k_p                 # N/m, kept: the ratio scales the other closures
        self.stiffness = Stiffness.reference(k_p, ratio, self.geom.n_limbs, self.geom.actuated)
        self.assembler = BatchAssembler(self.model, self.index, self.stiffness, gravity=gravity)

    def set_errors(self, errors: ErrorSet | dict) -> None:
        """Replace the machine's geometric errors (a fast in-place model edit, ~0.2 ms)."""
        if isinstance(errors, dict):
            errors = ErrorSet.from_dict(errors, self.geom.n_limbs, self.geom.actuated)
        self.errors = errors
        apply_errors(self.model, errors, self.geom, self.index, self._scratch)

    def set_stiffness_ratio(self, ratio: float) -> None:
        """Change the actuated-closure/SS over passive-closure stiffness ratio (the passive closures keep
        their stiffness; any ratio > 0, also below 1, where a fit may pass on its way)."""
        self.stiffness = Stiffness.reference(self.passive_stiffness, float(ratio), self.geom.n_limbs, self.geom.actuated)
        self.assembler.set_stiffness(self.stiffness)

    # ------------------------------------------------------------------ configuration guesses
    def initial_qpos(self, joint: np.ndarray, outside: str = "raise") -> np.ndarray:
        """Configurations (N, nq) near the equilibrium for true motor joint angles (N, 2) rad.

        A pose outside the workspace of the nominal machine raises ValueError (``outside="raise"``) or
        gets a row of NaN (``outside="nan"``).

        The pose comes from the nominal forward kinematics (:func:`start_orientation`: interpolated for
        small batches); the limb angles from the real IK of this machine at that pose. Within the error
        size (and the interpolation's 1e-3 rad) of the equilibrium, which the assembly then reaches.
        """
        geom = self.geom
        phi, theta = start_orientation(joint, geom)
        if np.any(~np.isfinite(theta)) and outside == "raise":
            bad = int(np.flatnonzero(~np.isfinite(theta))[0])
            raise ValueError(f"pose {bad}: motor angles {np.rad2deg(joint[bad]).round(3)} deg are outside "
                             "the workspace of the machine")
        r, R = nominal_pose(phi, theta, geom)
        q = self.pose_qpos(r, R, joint)
        q[~np.isfinite(theta)] = np.nan
        return q

    def pose_qpos(self, r: np.ndarray, R: np.ndarray, joint: np.ndarray | None = None) -> np.ndarray:
        """Configurations (N, nq) that put the platform at poses (r (N, 3) mm, R (N, 3, 3)): every limb's
        base angle from this machine's real IK (``joint`` (N, 2) rad, if given, for the motors instead),
        the SS limb and the links to match. Limbs whose IK has no solution there start at home."""
        geom, idx = self.geom, self.index
        N = len(r)
        q = np.tile(self.model.qpos0, (N, 1))
        ik = limb_ik(r, R, self.errors, geom, limbs=tuple(range(1, geom.n_limbs + 1)))
        beta = np.where(np.isfinite(ik.beta), ik.beta, np.deg2rad(-39.351))
        q[:, idx.qadr_base] = beta
        if joint is not None:
            q[:, idx.qadr_base[:2]] = joint
        # Universal joint at O: Rx(u1) Ry(u2) e_z = r / |r|; the ball takes the rest of R.
        n = r / np.linalg.norm(r, axis=1, keepdims=True)
        u2 = np.arcsin(np.clip(n[:, 0], -1, 1))
        u1 = np.arctan2(-n[:, 1], n[:, 2])
        qa = self.model.jnt_qposadr
        q[:, qa[mj_joint(self.model, "ss_u1")]] = u1
        q[:, qa[mj_joint(self.model, "ss_u2")]] = u2
        R_ball = np.swapaxes(rot_x(u1) @ rot_y(u2), 1, 2) @ R
        q[:, qa[idx.jnt_ball]:qa[idx.jnt_ball] + 4] = _mat2quat(np.where(np.isfinite(R_ball), R_ball, np.eye(3)))
        # Second links: direction S - A in the link frame R Q2_j = (cos g, 0, -sin g).
        Q2 = limb_frames(geom.psi, self.errors.dmu, self.errors.dnu)
        v = np.einsum("nji,nkj->nki", R, ik.S - ik.A)        # platform coordinates
        v = np.einsum("kji,nkj->nki", Q2, v)                  # link-2 local coordinates
        q[:, idx.qadr_plat] = np.arctan2(-v[..., 2], v[..., 0])
        return q

    # ------------------------------------------------------------------ driving
    def reach_joint(self, joint: np.ndarray, qpos: np.ndarray | None = None, outside: str = "raise") -> TwinState:
        """Assemble at true motor joint angles (N, 2) rad (after zero offsets and drive effects), from the
        configurations ``qpos`` (N, nq) or the closed-form start. A pose outside the workspace raises
        ValueError (``outside="raise"``) or comes back unconverged with NaN (``outside="nan"``; so do
        rows of ``qpos`` that are NaN)."""
        joint = np.atleast_2d(np.asarray(joint, float))
        q = self.initial_qpos(joint, outside) if qpos is None else np.array(qpos, dtype=float, copy=True)
        q[:, self.index.qadr_base[:2]] = joint
        inside = np.isfinite(q).all(axis=1)
        if inside.all():
            return self._state(self.assembler.solve(q), joint)
        state = self._empty_state(joint)
        if inside.any():
            part = self._state(self.assembler.solve(q[inside]), joint[inside])
            self.merge_state(state, part, inside)
        return state

    def merge_state(self, state: TwinState, part: TwinState, rows: np.ndarray) -> None:
        """Write the poses of ``part`` into ``state`` at ``rows`` (a mask or indices), in place."""
        for name in ("r", "R", "targets", "joint", "gaps", "ss_axial", "converged", "iterations", "qpos"):
            getattr(state, name)[rows] = getattr(part, name)

    def _empty_state(self, joint: np.ndarray) -> TwinState:
        """A state of N unconverged poses, every quantity NaN."""
        N, k, n = len(joint), len(self.index.site_targets), len(self.index.site_s1)
        nan = lambda *shape: np.full((N, *shape), np.nan)  # noqa: E731
        return TwinState(r=nan(3), R=nan(3, 3), targets=nan(k, 3), joint=joint.copy(), gaps=nan(n, 3),
                         ss_axial=nan(), converged=np.zeros(N, bool), iterations=np.zeros(N, int),
                         qpos=nan(self.model.nq))

    def reach(self, m_cmd_deg: np.ndarray) -> TwinState:
        """Drive to commanded motor angles (N, 2) deg; the joints go to command + zero offset."""
        joint = np.deg2rad(np.atleast_2d(np.asarray(m_cmd_deg, float))) + self.errors.dtheta[:2]
        return self.reach_joint(joint)

    def _state(self, res: AssemblyResult, joint: np.ndarray) -> TwinState:
        N = len(joint)
        xpos, xmat = self.assembler.bodies(N, self.index.platform)
        targets = self.assembler.sites(N, self.index.site_targets) / MM
        return TwinState(r=xpos / MM, R=xmat, targets=targets, joint=joint, gaps=res.gaps / MM,
                         ss_axial=res.ss_axial / MM, converged=res.converged,
                         iterations=res.iterations, qpos=res.qpos)


#: Batches smaller than this start from the tabulated forward kinematics (below: the Newton solve's
#: fixed cost of ~4 ms dominates; above: the solve is cheap per pose and the table would not pay).
SMALL_BATCH = 64
#: Spacing of the forward-kinematics table over the motor angles, rad (linear interpolation error
#: <= 8e-4 rad in pointing coordinates; the assembly converges from there in the same iterations).
TABLE_STEP = np.deg2rad(4.0)
_tables: dict[int, tuple] = {}


def _fk_table(geom: Geometry):
    """Pointing coordinates of the nominal forward kinematics on a motor-angle grid (built once per
    geometry, ~0.1 s): a linear interpolator, NaN outside the workspace."""
    key = id(geom)
    if key not in _tables or _tables[key][0] is not geom:
        from scipy.interpolate import RegularGridInterpolator

        b = np.arange(geom.motor_min, geom.motor_max + TABLE_STEP, TABLE_STEP)
        b1, b2 = np.meshgrid(b, b, indexing="ij")
        phi, theta = nominal_fk(np.stack([b1.ravel(), b2.ravel()], 1), geom)
        p = pointing_coords(phi, theta).reshape(len(b), len(b), 2)
        _tables[key] = (geom, RegularGridInterpolator((b, b), p, bounds_error=False, fill_value=np.nan))
    return _tables[key][1]


def start_orientation(joint: np.ndarray, geom: Geometry) -> tuple[np.ndarray, np.ndarray]:
    """Nominal forward kinematics (phi, theta) rad at motor angles (N, 2) rad, for a starting guess.

    Batches under :data:`SMALL_BATCH` poses interpolate a table of :func:`nominal_fk` (accurate to
    ~1e-3 rad, 0.1 ms instead of ~4 ms per call); larger batches and poses next to the workspace
    boundary solve :func:`nominal_fk` (NaN outside the workspace).
    """
    if len(joint) >= SMALL_BATCH:
        return nominal_fk(joint, geom)
    phi, theta = from_pointing_coords(_fk_table(geom)(joint))
    off = ~np.isfinite(theta)
    if off.any():
        phi[off], theta[off] = nominal_fk(joint[off], geom)
    return phi, theta


def mj_joint(m, name: str) -> int:
    return mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)


def _mat2quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) → unit quaternions (N, 4), w first (MuJoCo convention)."""
    from scipy.spatial.transform import Rotation

    xyzw = Rotation.from_matrix(R).as_quat()
    return np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)


def render_png(qpos: np.ndarray | None = None, errors=None, width: int = 800, height: int = 600,
               azimuth: float = 135.0, elevation: float = -22.0, distance: float = 1.35,
               lookat=(0.0, 0.0, 0.22)) -> bytes:
    """PNG image of the over-constrained PM (scene with floor and light) at configuration ``qpos`` (default
    home) with geometric ``errors`` (an :class:`ErrorSet`; default none)."""
    m = load_model(SCENE_XML)
    geom = default_geometry()
    apply_errors(m, errors if errors is not None else ErrorSet(), geom, ModelIndex.of(m, geom.n_limbs))
    d = mujoco.MjData(m)
    d.qpos[:] = m.key_qpos[0] if qpos is None else qpos
    mujoco.mj_forward(m, d)
    cam = mujoco.MjvCamera()
    cam.azimuth, cam.elevation, cam.distance = azimuth, elevation, distance
    cam.lookat[:] = lookat
    return render_model_png(m, d, width, height, cam)
