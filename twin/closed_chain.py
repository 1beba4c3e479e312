"""Any closed-chain machine from its MJCF and machine.toml: assembly, exact derivatives, forward and inverse.

:class:`ClosedChainTwin` reads the kinematic tree and the loop closures from the compiled MuJoCo model
(active equality constraints: site-based ``connect``, 3 equations each, and ``weld``, 6 each; body-based
ones are turned site-based on load, :mod:`pmcal.twin.closures`) and the motors, targets and task from a :class:`pmcal.mechanism.machine_spec.MachineSpec`. Nothing
in it is specific to a machine.

**Geometric errors** (``docs/machine_toml.md``, section ``[errors]``; :mod:`pmcal.twin.frame_errors`) are
small displacements of frames of the model: a body frame carries ``dx, dy, dz`` (mm) and ``drx, dry, drz``
(deg), a translation along and a rotation vector about its *parent's* axes through the body's frame origin
(``body_pos``; joints, geoms and sites written in the body frame move with it); a site carries ``dx, dy,
dz`` (mm) in its body's frame; a motor a zero offset ``mK.dzero`` (deg or mm): joint position = command -
zero + dzero. Errors are applied by editing the compiled ``body_pos``, ``body_quat`` and ``site_pos`` (no
recompilation; nothing else of the model depends on them for kinematics).

**Assembly** (:meth:`solve`): with the motor joints held, Newton (Gauss-Newton with a minimum-norm step, so
an over-constrained chain settles on the least-squares compromise) on the closure equations over the
passive degrees of freedom, from the nearest earlier solution (warm start) or, failing that, by
continuation from the ``home`` keyframe: every solve stays on the assembly branch of ``home``. Residuals
and Jacobians come from MuJoCo (``mj_kinematics``, ``mj_comPos``, ``mj_jacSite``); quaternion joints are
stepped with ``mj_integratePos``.

**Compliant closures** (optional ``[closures]`` of the machine.toml, for over-constrained machines whose
loops conflict once they carry errors): the rows are weighted by the square roots of the closure
stiffnesses (N/m), passive joints with an MJCF ``stiffness`` add spring rows, and the assembly is the
least-squares equilibrium of that elastic energy (converged when the Newton step vanishes).

**Derivatives** (:meth:`jacobian`) by the implicit-function theorem at the assembled configuration: with
(weighted) closure equations ``c(q_p, q_m, p) = 0``,

    dq_p/dp = -C_p^+ (dc/dp),      d y/dp = J_y,p dq_p/dp + dy/dp|_q

(for conflicting closures, compliant or closed along their independent directions, the loops keep a gap and
the derivative gains the gap's second-order terms, :meth:`_strain_terms`; docs/closed_chain.md "Derivatives")

where ``C_p`` is the closure Jacobian over the passive dofs (MuJoCo), ``dc/dp`` and ``dy/dp|_q`` the
derivatives of the closure points and targets with respect to the frame errors at fixed joints, in
closed form from the frames' world poses (a translation error moves every point of the frame's subtree
along the parent axis; a rotation error turns it about the frame origin, the axis mapped through the left
Jacobian of SO(3) at the current error so the derivative is exact at any error, not only at zero).
No finite differences of the solve and no recompiling; the tests check it against central differences.

**Inverse kinematics** (:meth:`inverse`): Newton on the closure equations together with the task
equations over all dofs, from ``home`` with continuation along the straight task-space path when the
direct step fails; NaN and a reason (:meth:`inverse_report`) where no assembly reaches the target or a
motor would leave its range.

Units at the interface: commands deg / mm, targets mm (world frame = base frame), task coordinates as
named, errors mm / deg. Inside MuJoCo: SI.

Example
-------
>>> from pmcal.mechanism.machine_spec import MachineSpec
>>> from pmcal.mjcf import machine_dir
>>> twin = ClosedChainTwin(MachineSpec.load(machine_dir("delta_3dof")))
>>> cmd = twin.sample_commands(48, np.random.default_rng(3))         # (48, 3) deg
>>> y = twin.targets(cmd, {"arm1.dz": 0.2})                          # (48, 3, 3) mm
>>> J = twin.jacobian(cmd, None, ["arm1.dz", "m1.dzero"])             # (48, 3, 3, 2) mm/mm, mm/deg
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import mujoco
import numpy as np
from scipy.spatial import cKDTree

from pmcal.errors import InputError
from pmcal.mechanism.machine_spec import MachineSpec
from pmcal.mechanism.rigid import fit_pose
from pmcal.mechanism.rotations import rotvec_matrix
from pmcal.mechanism.task_space import POSITION, task_coordinates, task_difference
from pmcal.twin.closures import solve_stacked
from pmcal.twin.closures import compile_with_site_closures
from pmcal.twin.export import CALIBRATED_TOML_START
from pmcal.twin.frame_errors import DEG, MM, FrameErrors
from pmcal.twin.overconstraint import redundant_directions

#: custom numeric of an exported model: the redundant closure directions of the machine it was calibrated
#: from (rows of ``n_equations`` numbers, :meth:`ClosedChainTwin._read_redundancy`)
REDUNDANT_NUMERIC = "pmcal_redundant_directions"
#: custom numeric export-model writes into every model it exports: the identified machine, whose errors may
#: leave its loops strained and couple free rod spins to the nests slightly (a model as drawn does neither)
IDENTIFIED_NUMERIC = "pmcal_identified_machine"

_OBJ = mujoco.mjtObj
_EQ = mujoco.mjtEq
_JNT = mujoco.mjtJoint



@dataclass(frozen=True)
class Closure:
    """One loop closure: equality ``name`` between sites ``site1`` and ``site2`` (ids); ``weld`` adds the
    three orientation equations to the three position ones."""

    name: str
    site1: int
    site2: int
    weld: bool


@dataclass
class Kinematics:
    """World poses at assembled configurations (N poses, SI), what :meth:`ClosedChainTwin.jacobian` needs.

    qpos (N, nq); xpos (N, nbody, 3); xmat (N, nbody, 3, 3); site_xpos (N, npoint, 3), site_xmat
    (N, npoint, 3, 3) and jacp, jacr (N, npoint, 3, nv) of the twin's points (closure sites, targets, task
    site; :attr:`ClosedChainTwin.points`).
    """

    qpos: np.ndarray
    xpos: np.ndarray
    xmat: np.ndarray
    site_xpos: np.ndarray
    site_xmat: np.ndarray
    jacp: np.ndarray
    jacr: np.ndarray


class ClosedChainTwin:
    """The digital twin of a closed-chain machine described as data (see module docstring).

    Parameters
    ----------
    spec : a loaded, non-legacy :class:`~pmcal.mechanism.machine_spec.MachineSpec`.
    model : an already compiled model of ``spec.model_path`` (default: compiled here).

    Attributes
    ----------
    spec, model : the machine and its compiled MuJoCo model (SI; errors are applied in place).
    error_keys : every geometric error of the machine, ``"<frame>.<component>"`` and ``"mK.dzero"``.
    closures : the loop closures read from the model.
    sigma_mm : tracker noise from the spec, mm.
    """

    #: Closure residual (m, largest component) below which a configuration counts as assembled.
    TOL_M = 1e-12
    MAX_ITER = 40
    #: Largest Newton step per coordinate (rad or m); longer steps are scaled down.
    MAX_STEP = 0.2
    #: Largest motor move per continuation sub-step, as a fraction of the motor's range (the task-space
    #: path of the inverse kinematics: of the workspace box).
    PATH_STEP = 0.1
    #: A target farther than this from every assembled pose, in sizes of the workspace box, is out of reach
    #: without a walk of thousands of sub-steps (a box in metres: minutes per target). Machines' homes lie
    #: within 1.1 box sizes of every corner of their box.
    MAX_PATH_BOXES = 100.0
    #: :meth:`sample_commands` gives up when none of this many drawn poses is reachable (a workspace box off
    #: the machine, motor ranges that exclude it): its 20 rounds would take minutes and find none either
    HOPELESS_DRAWS = 200

    def __init__(self, spec: MachineSpec, model: mujoco.MjModel | None = None):
        if spec.legacy:
            raise ValueError(f"{spec.name} is a seeded machine with its own code (kind {spec.kind!r})")
        self.spec = spec
        self.sigma_mm = float(spec.sigma_mm)
        self.model = model if model is not None else compile_with_site_closures(spec.model_path)
        m = self.model
        self.data = mujoco.MjData(m)
        self._file = str(spec.model_path)
        # home's projection of the closure rows off their redundant directions, or None (no redundancy, or
        # [closures] compliance); solves project at each configuration (_local_keep), this one serves a
        # residual without its Jacobian (at home)
        self._keep = None
        self._read_motors()
        self._read_closures()
        self._read_sites()
        self._check_site_parts()
        self.home_qpos = self._read_home()
        self._read_redundancy()
        self._check_home_closes()
        self._check_mobility()
        # Under frames = "all" the closure sites carry errors; the tracker nests do not (they define the
        # moving frames they sit on: their coordinates there come from a CMM or the drawing), nor does the
        # task site unless it closes a loop (it is not measured).
        error_sites = [int(p) for p in self.points[:self._n_closure_points] if p not in self.target_sites]
        #: the geometric errors (:class:`pmcal.twin.frame_errors.FrameErrors`)
        self.errors = FrameErrors(spec, m, self.points, error_sites, self.motor_dof, self.motor_unit)
        #: every geometric error of the machine, ``"<frame>.<component>"`` and ``"mK.dzero"``
        self.error_keys = self.errors.keys
        if not self.error_keys:     # every campaign, plan and fit is about them (was a reshape error, exit 1)
            raise InputError("leaves no error to identify (frames, exclude and components select no frame, and "
                             "motor_zero = false): list frames, or set motor_zero = true",
                             file=str(spec.folder / "machine.toml"), field="errors")
        self._warm_cmd = np.zeros((0, self.n_motors))
        self._warm_qpos = np.zeros((0, m.nq))
        self.home_commands = self._commands_of(self.home_qpos[None])[0]
        self._read_task_frame()

    def _read_redundancy(self) -> None:
        """The closure equations' redundant directions at ``home`` (:mod:`pmcal.twin.overconstraint`), and
        without ``[closures]`` compliance the projection that closes the loops along the others only.

        A model pmcal exported (``export-model``) carries the directions of the machine it was calibrated
        from in the custom numeric :data:`REDUNDANT_NUMERIC`: which of a loop's equations its joints' play
        takes up is the design's, not the errors'. Its geometry holds the identified errors, which tilt a
        planar loop's axes out of parallel, so at its own home the directions would differ (a rigid tilted
        four-bar does not move at all), and the exported machine would not be the identified one."""
        stored = mujoco.mj_name2id(self.model, _OBJ.mjOBJ_NUMERIC, REDUNDANT_NUMERIC)
        if stored >= 0:
            D = self._stored_redundancy(stored)
        else:
            jp, jr = self._kin(self.home_qpos, closure_only=True)
            C = self._closure(jp, jr)[1][: self.n_equations]
            D = redundant_directions(C[:, self.passive])
        #: (n_redundant, n_equations) unit rows: equation combinations no joint motion changes at home
        self.redundant_directions = D
        if len(D) and not self.spec.closures:
            self._keep = np.eye(self.n_equations) - D.T @ D

    def _stored_redundancy(self, index: int) -> np.ndarray:
        """The redundant directions (n, n_equations) of the custom numeric ``index``; InputError naming the
        file when they do not fit this model's closures."""
        m = self.model
        adr, size = int(m.numeric_adr[index]), int(m.numeric_size[index])
        data = np.array(m.numeric_data[adr: adr + size], float)
        D = data.reshape(-1, self.n_equations) if self.n_equations and size % self.n_equations == 0 else None
        if D is None or not np.allclose(D @ D.T, np.eye(len(D)), atol=1e-6):
            raise InputError(f"custom numeric {REDUNDANT_NUMERIC} holds {size} numbers, not orthonormal rows of "
                             f"this model's {self.n_equations} closure equations (written by export-model for "
                             "the model it exported; remove it to have them found at home)", file=self._file,
                             field=REDUNDANT_NUMERIC)
        return D

    #: Closure residual (m) up to which the model's default configuration counts as closed when there is no
    #: ``home`` keyframe (a CAD export's rounding: 1e-7 m on Reachy Mini); it is then assembled exactly. A
    #: ``home`` keyframe open by more is refused (:meth:`_check_home_closes`).
    HOME_TOL_M = 1e-5

    def _read_home(self) -> np.ndarray:
        """The configuration every solve starts from (nq,): the ``home`` keyframe, or without one the model's
        default configuration ``qpos0`` (a CAD export's assembled pose) closed by Newton with the motors held;
        InputError naming the model when it is not within :data:`HOME_TOL_M` of closing."""
        m = self.model
        if self.spec.home is not None:
            q = m.key_qpos[mujoco.mj_name2id(m, _OBJ.mjOBJ_KEY, self.spec.home)].copy()
            bad = np.flatnonzero(~np.isfinite(q))
            if bad.size:
                raise InputError(f"keyframe {self.spec.home!r}: qpos value {bad[0] + 1} of {m.nq} is {q[bad[0]]} "
                                 "(an assembled configuration is finite numbers)", file=self._file, field="keyframe")
            return q
        q0 = m.qpos0.copy()
        gap, _ = self._gap_at(q0)
        q, ok = self._newton(q0)
        if gap > self.HOME_TOL_M or not ok:
            raise InputError(f"no 'home' keyframe and the model's default configuration does not close its "
                             f"loops (gap {gap * 1e3:.3g} mm): add an assembled <key name=\"home\" qpos=...> "
                             f"(docs/machine_toml.md)", file=self._file, field="keyframe")
        return q

    @functools.cached_property
    def _exported(self) -> bool:
        """Whether the model is an identified machine export-model wrote (:data:`IDENTIFIED_NUMERIC`, the
        redundant directions it stores, or its machine.toml's first words), not a model as drawn."""
        if any(mujoco.mj_name2id(self.model, _OBJ.mjOBJ_NUMERIC, n) >= 0
               for n in (IDENTIFIED_NUMERIC, REDUNDANT_NUMERIC)):
            return True
        toml = Path(self.spec.folder) / "machine.toml" if self.spec.folder is not None else None
        return bool(toml and toml.is_file() and toml.read_text(encoding="utf-8").startswith(CALIBRATED_TOML_START))

    def _check_home_closes(self) -> None:
        """InputError naming the gap when the ``home`` keyframe leaves a rigid loop open by more than
        :data:`HOME_TOL_M`, as the default configuration may not (:meth:`_read_home`): a machine as drawn
        closes every equation at home, a redundant one too (the redundant directions found at an open
        keyframe can hold its whole gap: 57 mm on Gepetto's kangaroo_like leg). A model export-model wrote
        (its redundant directions stored, :data:`REDUNDANT_NUMERIC`) is the identified machine, whose loops
        keep the strain its errors leave: only the directions the twin closes there count
        (:meth:`_local_keep`). Every solve would start off the assembly and land on whichever one Newton
        finds (the keyframe's motor values then name no pose of the machine), and the mobility check would
        judge an open assembly's free joints. Compliant closures (``[closures]``) settle with a
        gap and are not checked."""
        if self.spec.home is None or self.spec.closures is not None:
            return
        if self._exported:
            jp, jr = self._kin(self.home_qpos, closure_only=True)
            gap = float(np.max(np.abs(self._closure(jp, jr)[0][:self.n_equations]), initial=0.0))
        else:
            gap = self._gap_at(self.home_qpos)[0]
        if gap > self.HOME_TOL_M:
            raise InputError(f"keyframe {self.spec.home!r} does not close the loops (gap "
                             f"{self._gap_at(self.home_qpos)[1]}): store an assembled configuration, every "
                             f"closure met (docs/machine_toml.md, [machine] home)", file=self._file, field="keyframe")

    def _gap_at(self, q: np.ndarray) -> tuple[float, str]:
        """The largest closure gap at the configuration ``q`` (nq,) (m; rad for a weld's rotation), and the
        largest of the positions and of the welds' rotations in words (``"746 mm at loop1, 162 deg at loop2"``)."""
        self._kin(q, jac=False)
        d = self.data
        r = np.abs(self._gaps(d.site_xpos[self.points][None],
                              d.site_xmat[self.points].reshape(1, -1, 3, 3) if self._weld.any() else None)[0])
        names = [c.name for c in self.closures] + [c.name for c in self.closures if c.weld]
        n_pos = 3 * len(self.closures)
        words = []
        for part, scale, unit in ((slice(0, n_pos), 1e3, "mm"), (slice(n_pos, None), np.degrees(1.0), "deg")):
            if r[part].size:
                i = int(np.argmax(r[part]))
                words.append(f"{r[part][i] * scale:.3g} {unit} at {names[(part.start + i) // 3]}")
        return float(r.max()), ", ".join(words)

    #: Relative size (of the largest singular value) below which a direction of the passive dofs counts as
    #: free of the closures, and motion (m per unit, of the nests or the task site) above which it matters:
    #: FREE_MOVES_M, or FREE_MOVES_SHARE of the machine's size (its bodies' extent at home) if larger. A
    #: missing motor moves the nests by about a link's length per radian; a ball-ball rod's free spin moves
    #: them not at all on the drawing, and by about the size of the geometric errors per radian on a machine
    #: whose joint axes the errors moved (a calibrated model, export-model: 0.1 mm/rad on gepetto_wl16).
    FREE_RTOL, FREE_MOVES_M, FREE_MOVES_SHARE = 1e-9, 1e-9, 0.01
    #: motion (m per unit) above which a free direction matters on a model as drawn (not an export-model output,
    #: whose errors couple free rod spins to the nests slightly): every model as drawn here shows none (below
    #: 1e-9 m/rad); LAAS's Disney-like leg, a hinge drawn 0.295 mm off a ball's centre (_near_axis), 2e-4 to
    #: 6e-4 m/rad, its solves then landing 0.06 mm apart depending on where they start
    FREE_MOVES_DRAWN_M = 1e-6

    def _check_mobility(self) -> None:
        """InputError naming the joints when, at ``home``, the closures leave a direction of the passive dofs
        free that moves the tracker nests or the task site: an actuated joint missing from ``[[motors]]``.
        Free directions that move neither (a ball-ball rod's spin about its axis, an unactuated side chain
        such as an antenna or a gripper finger) are allowed: every solve leaves them where they are."""
        jp, jr = self._kin(self.home_qpos)
        free = self._free_directions(jp, jr)                            # (npassive, nfree)
        #: passive directions the closures leave free at home (a ball-ball rod's spin): every solve leaves
        #: them where they are, so where a calibrated model's errors couple them to the nests, slightly
        #: (0.1 mm/rad), the nests depend on the path a solve took, by far less than the tracker noise
        self.n_free = int(free.shape[1])
        if not free.size:
            return
        extent = float(np.linalg.norm(np.ptp(self.data.xpos[1:], axis=0))) if self.model.nbody > 1 else 0.0
        seen = np.arange(self._n_closure_points, len(self.points))       # the nests and the task site: where
        turns = [self._task_p] if set(self.spec.task.coordinates) - set(POSITION) else []   # ... and its turn
        moves = np.concatenate([jp[seen], jr[turns] * max(extent, 1.0)])[..., self.passive]   # m per unit
        motion = moves.reshape(-1, len(self.passive)) @ free             # (rows, nfree)
        limit = max(self.FREE_MOVES_M, self.FREE_MOVES_SHARE * extent) if self._exported else self.FREE_MOVES_DRAWN_M
        if np.max(np.abs(motion), initial=0.0) <= limit:
            return
        u, _, _ = np.linalg.svd(motion.T @ motion)
        direction = free @ u[:, 0]                                       # the free direction that moves most
        dof = self.passive[np.argsort(-np.abs(direction))]
        jnt = self.model.dof_jntid[dof]
        names = list(dict.fromkeys(mujoco.mj_id2name(self.model, _OBJ.mjOBJ_JOINT, int(j)) or f"joint {j}"
                                   for j in jnt[:3]))
        head = (f"the loops leave joint {names[0]} free and it moves the tracker nests or the task site "
                f"(with {', '.join(names[1:]) or 'no other joint'}; {np.max(np.abs(motion)) * 1e3:.3g} mm/rad at home)")
        near = self._near_axis(self.passive[np.abs(direction) > 0.1 * np.abs(direction).max()], extent)
        if near:
            raise InputError(f"{head}: {near}, so the model nearly repeats a rotation: a drawing whose axes almost "
                             "meet, not a pose (no home helps): put the axis through that centre or make one of the "
                             "two joints fixed", file=str(self.spec.folder / "machine.toml"), field="motors")
        raise InputError(f"{head}: list it under [[motors]] if it is actuated, close the loop that should hold it, "
                         "or store a home away from a singular pose (a leg folded or stretched)",
                         file=str(self.spec.folder / "machine.toml"), field="motors")

    #: distance (m) below which a joint's anchor counts as on another's axis (the drawing's precision:
    #: 6 significant digits of a 1 m machine), and share of the machine's size (1 mm on a 1 m leg) below
    #: which a larger one is an axis that nearly meets it (LAAS's Disney-like leg: a hinge 0.295 mm from a
    #: ball's centre, which no home frees the nests from)
    ON_AXIS_M, NEAR_AXIS_SHARE = 1e-6, 0.001

    def _near_axis(self, dofs: np.ndarray, extent: float) -> str:
        """In words, the hinge among the degrees of freedom ``dofs`` whose axis passes nearest another of
        their joints' anchors, off it by more than ON_AXIS_M and less than NEAR_AXIS_SHARE of ``extent``
        (the machine's size, m) at the configuration last computed (home); "" if none does."""
        m, d = self.model, self.data
        jnts = [int(j) for j in dict.fromkeys(m.dof_jntid[dofs])]
        best = (self.NEAR_AXIS_SHARE * extent, "")
        for a in (j for j in jnts if m.jnt_type[j] == _JNT.mjJNT_HINGE):
            for b in jnts:
                v = d.xanchor[b] - d.xanchor[a]
                off = float(np.linalg.norm(v - d.xaxis[a] * (v @ d.xaxis[a])))
                if self.ON_AXIS_M < off < best[0]:
                    best = (off, f"joint {mujoco.mj_id2name(m, _OBJ.mjOBJ_JOINT, a)}'s axis passes {off * 1e3:.3g} "
                                 f"mm from joint {mujoco.mj_id2name(m, _OBJ.mjOBJ_JOINT, b)}'s anchor")
        return best[1]

    def _read_task_frame(self) -> None:
        """World pose (m, rotation matrix) of the frame task coordinates are written in: ``[task] frame``, a
        site on the fixed base, taken on the nominal model at home; the world frame without it."""
        self._frame_p, self._frame_R = np.zeros(3), np.eye(3)
        if self.spec.task.frame:
            sid = mujoco.mj_name2id(self.model, _OBJ.mjOBJ_SITE, self.spec.task.frame)
            self._kin(self.home_qpos, jac=False)
            self._frame_p = self.data.site_xpos[sid].copy()
            self._frame_R = self.data.site_xmat[sid].reshape(3, 3).copy()

    def _in_task_frame(self, p_m: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions (..., 3) m and orientations (..., 3, 3) in world -> in the task frame."""
        return (p_m - self._frame_p) @ self._frame_R, self._frame_R.T @ R

    @classmethod
    def from_folder(cls, folder) -> "ClosedChainTwin":
        """The twin of the machine folder ``folder`` (``MachineSpec.load(folder)``; InputError if invalid)."""
        return cls(MachineSpec.load(folder))

    # ------------------------------------------------------------------ structure
    def _read_motors(self) -> None:
        m = self.model
        jids, units = [], []
        for mot in self.spec.motors:
            j = mujoco.mj_name2id(m, _OBJ.mjOBJ_JOINT, mot.joint)
            want = _JNT.mjJNT_HINGE if mot.kind == "revolute" else _JNT.mjJNT_SLIDE
            if j < 0 or m.jnt_type[j] != want:
                raise InputError(f"motor joint {mot.joint!r} is not a {mot.kind} joint of the compiled model",
                                 file=self._file, field=f"{mot.name}.joint")
            jids.append(j)
            units.append(DEG if mot.kind == "revolute" else MM)
        self.motor_joints = np.array(jids, int)
        self.motor_qadr = m.jnt_qposadr[self.motor_joints].astype(int)
        self.motor_dof = m.jnt_dofadr[self.motor_joints].astype(int)
        self.motor_unit = np.array(units)                 # SI per command unit
        self.motor_zero = np.array([mot.zero for mot in self.spec.motors], float)
        self.motor_range = np.array([mot.range for mot in self.spec.motors], float)
        self.n_motors = len(jids)
        self.passive = np.setdiff1d(np.arange(m.nv), self.motor_dof)

    def _read_closures(self) -> None:
        m = self.model
        out, couplings = [], []
        for e in range(m.neq):
            name = mujoco.mj_id2name(m, _OBJ.mjOBJ_EQUALITY, e) or f"equality {e}"
            if not m.eq_active0[e]:
                continue
            kind = int(m.eq_type[e])
            if kind == _EQ.mjEQ_JOINT:
                couplings.append(e)
                continue
            if kind not in (_EQ.mjEQ_CONNECT, _EQ.mjEQ_WELD):
                raise InputError("only connect, weld and joint equalities can close loops (make other "
                                 "equalities inactive, active=\"false\")", file=self._file, field=name)
            if int(m.eq_objtype[e]) != _OBJ.mjOBJ_SITE:      # body-based ones are converted on load
                raise InputError("a loop closure must join two sites or two bodies", file=self._file, field=name)
            out.append(Closure(name, int(m.eq_obj1id[e]), int(m.eq_obj2id[e]), kind == _EQ.mjEQ_WELD))
        if not out:
            raise InputError("the model has no active connect/weld equality: no loop to close",
                             file=self._file)
        self.closures = tuple(out)
        self.n_equations = sum(6 if c.weld else 3 for c in out)
        self._read_compliance()
        self._read_couplings(couplings)

    def _read_couplings(self, eqs: list[int]) -> None:
        """Joint equalities ``eqs`` (a gripper's two drivers moved as one): rows ``q1 - q1_0 - poly(q2 - q2_0)``
        (rad or m; MuJoCo's ``polycoef``, ``q_0`` the model's ``qpos0``), with the passive joint springs in
        :meth:`_joint_rows`."""
        m = self.model
        j1 = m.eq_obj1id[eqs].astype(int)
        j2 = m.eq_obj2id[eqs].astype(int)
        self._cpl_q1, self._cpl_d1 = m.jnt_qposadr[j1].astype(int), m.jnt_dofadr[j1].astype(int)
        has2 = j2 >= 0
        j2 = np.where(has2, j2, j1)
        self._cpl_q2, self._cpl_d2 = m.jnt_qposadr[j2].astype(int), m.jnt_dofadr[j2].astype(int)
        self._cpl_has2 = has2
        self._cpl_ref1, self._cpl_ref2 = m.qpos0[self._cpl_q1].copy(), m.qpos0[self._cpl_q2].copy()
        self._cpl_poly = m.eq_data[eqs, :5].copy()

    def _joint_rows(self, qpos: np.ndarray, with_jac: bool = True):
        """Rows on joint coordinates of A configurations ``qpos`` (A, nq): the passive joint springs
        ``sqrt(k_j) (q_j - ref_j)`` and the joint equalities (:meth:`_read_couplings`), with their Jacobians
        (A, rows, nv) (None without ``with_jac``). They do not depend on the frame errors."""
        A, nv = len(qpos), self.model.nv
        ns, nc = len(self._spring_dof), len(self._cpl_q1)
        r = np.zeros((A, ns + nc))
        J = np.zeros((A, ns + nc, nv)) if with_jac else None
        r[:, :ns] = self._spring_sqrt_k * (qpos[:, self._spring_qadr] - self._spring_ref)
        x = np.where(self._cpl_has2, qpos[:, self._cpl_q2] - self._cpl_ref2, 0.0)          # (A, nc)
        powers = x[..., None] ** np.arange(5)                                              # (A, nc, 5)
        r[:, ns:] = qpos[:, self._cpl_q1] - self._cpl_ref1 - np.einsum("ack,ck->ac", powers, self._cpl_poly)
        if with_jac:
            J[:, np.arange(ns), self._spring_dof] = self._spring_sqrt_k
            rows = ns + np.arange(nc)
            J[:, rows, self._cpl_d1] = 1.0
            slope = np.einsum("ack,ck->ac", powers[..., :4], self._cpl_poly[:, 1:] * np.arange(1, 5))
            J[:, rows, self._cpl_d2] -= np.where(self._cpl_has2, slope, 0.0)
        return r, J

    def _read_compliance(self) -> None:
        """Row weights of the closure equations (sqrt of the stiffness, N/m) and the passive joint springs
        of ``spec.closures`` (none: unit weights, rigid closures)."""
        m, cs = self.model, self.spec.closures
        k_pos = [cs.stiffness.get(c.name, cs.default_n_per_mm) / MM if cs else 1.0 for c in self.closures]
        rows = [np.full(3, k) for k in k_pos] + [np.full(3, k) for k, c in zip(k_pos, self.closures) if c.weld]
        self._sqrt_w = np.sqrt(np.concatenate(rows))
        springs = []
        if cs and cs.joint_springs:
            for j in range(m.njnt):
                if (m.jnt_stiffness[j] > 0 and int(m.jnt_type[j]) in (_JNT.mjJNT_HINGE, _JNT.mjJNT_SLIDE)
                        and j not in self.motor_joints):
                    springs.append(j)
        self._spring_qadr = m.jnt_qposadr[springs].astype(int)
        self._spring_dof = m.jnt_dofadr[springs].astype(int)
        self._spring_sqrt_k = np.sqrt(m.jnt_stiffness[springs])
        self._spring_ref = m.qpos_spring[self._spring_qadr].copy()
        #: weight of the task equations in inverse kinematics: far above every closure (met exactly)
        self._task_sqrt_w = 1e3 * max(float(self._sqrt_w.max()), float(self._spring_sqrt_k.max(initial=0.0))) \
            if cs else 1.0

    def _read_sites(self) -> None:
        m = self.model
        sid = lambda n: mujoco.mj_name2id(m, _OBJ.mjOBJ_SITE, n)  # noqa: E731
        self.target_sites = np.array([sid(t) for t in self.spec.targets], int)
        self.task_site = sid(self.spec.task.site)
        pts: list[int] = []
        for s in [c.site1 for c in self.closures] + [c.site2 for c in self.closures] + list(self.target_sites) \
                + [self.task_site]:
            if s not in pts:
                pts.append(int(s))
        #: Site ids whose poses and Jacobians every solve computes (closure sites, targets, task site).
        self.points = np.array(pts, int)
        self._n_closure_points = len({c.site1 for c in self.closures} | {c.site2 for c in self.closures})
        pos = {s: i for i, s in enumerate(pts)}
        self._c1 = np.array([pos[c.site1] for c in self.closures])
        self._c2 = np.array([pos[c.site2] for c in self.closures])
        self._weld = np.array([c.weld for c in self.closures])
        self._tp = np.array([pos[s] for s in self.target_sites])
        self._task_p = pos[self.task_site]
        self.n_targets = len(self.target_sites)

    def _check_site_parts(self) -> None:
        """InputError naming the machine.toml key when a site sits on the wrong part: the task site or a
        tracker nest on the fixed base (they would not move with the motors: a demo reported 0 mm before and
        after), a ``[task] frame`` on a moving part, the two ends of a ``distance`` scale or the nests of a
        ``pose`` fit on different parts (one part, one rigid fit; a scale on one part reads nothing)."""
        m, spec = self.model, self.spec
        part = lambda s: int(m.body_weldid[m.site_bodyid[s]])  # noqa: E731
        body = lambda s: mujoco.mj_id2name(m, _OBJ.mjOBJ_BODY, int(m.site_bodyid[s])) or "world"  # noqa: E731
        fail = lambda key, text: InputError(text, file=str(spec.folder / "machine.toml"), field=key)  # noqa: E731
        if part(self.task_site) == 0:
            raise fail("task.site", f"site {spec.task.site!r} is on the fixed base (body {body(self.task_site)}): "
                                    "the task site must move with the motors (the tool centre point, the platform)")
        if spec.task.frame:
            s = mujoco.mj_name2id(m, _OBJ.mjOBJ_SITE, spec.task.frame)
            if part(s) != 0:
                raise fail("task.frame", f"site {spec.task.frame!r} is on body {body(s)}, which moves: the task "
                                         "frame is a site on the fixed base (the frame of the machine's drawing)")
        parts = [part(s) for s in self.target_sites]
        if spec.measure == "distance":
            if parts[0] == parts[1]:
                raise fail("tracker.targets", f"the scale's ends {spec.targets[0]!r} and {spec.targets[1]!r} are "
                                              f"on one rigid part (body {body(self.target_sites[0])}): their "
                                              "distance never changes")
            return
        for k, (name, s, p) in enumerate(zip(spec.targets, self.target_sites, parts), 1):
            if p == 0:
                raise fail(f"tracker.targets[{k}]", f"site {name!r} is on the fixed base (body {body(s)}): a nest "
                                              "measures a moving part")
        if spec.measure == "pose" and len(set(parts)) > 1:
            k = parts.index(next(p for p in parts if p != parts[0]))
            raise fail("tracker.targets", f"'pose' fits one rigid part to the nests, but {spec.targets[0]!r} is on "
                                          f"body {body(self.target_sites[0])} and {spec.targets[k]!r} on body "
                                          f"{body(self.target_sites[k])} (measure = \"position\" reads each nest)")

    # ------------------------------------------------------------------ parameters
    def error_units(self, keys: list[str] | None = None) -> list[str]:
        """Unit of each error key (``"mm"`` or ``"deg"``); default every :attr:`error_keys`."""
        return self.errors.units(keys)

    def prior_std(self, keys: list[str] | None = None) -> np.ndarray:
        """Prior size (1 sigma) of each key in its unit, from ``[errors]`` of the machine.toml."""
        return self.errors.prior_std(keys)

    def set_params(self, params: Mapping[str, float] | None) -> None:
        """Apply geometric errors ``{key: value}`` (mm / deg; missing keys 0, None: nominal) to the model.
        The warm starts stay: configurations of a machine with slightly other errors are the best starts."""
        self.errors.apply(params)

    @property
    def params(self) -> dict[str, float]:
        """The errors currently applied (non-zero ones), ``{key: value}`` mm / deg."""
        return {k: float(v) for k, v in zip(self.error_keys, self.errors.x) if v != 0.0}

    # ------------------------------------------------------------------ commands <-> joints
    def _joints_of(self, commands: np.ndarray) -> np.ndarray:
        """Motor joint positions (N, M) SI of commands (N, M)."""
        return (commands - self.motor_zero + self.errors.zero_offset) * self.motor_unit

    def _commands_of(self, qpos: np.ndarray) -> np.ndarray:
        return qpos[:, self.motor_qadr] / self.motor_unit + self.motor_zero - self.errors.zero_offset

    def _as_commands(self, commands) -> np.ndarray:
        c = np.atleast_2d(np.asarray(commands, float))
        if c.shape[-1] != self.n_motors:
            raise ValueError(f"commands need {self.n_motors} columns (m1..m{self.n_motors}), got shape {c.shape}")
        return c

    # ------------------------------------------------------------------ kinematics of one configuration
    def _kin(self, q: np.ndarray, jac: bool = True, closure_only: bool = False):
        """Forward kinematics at ``q``; with ``jac`` the points' Jacobians (3, nv) each (with
        ``closure_only`` those of the closure sites only, the first points; the others stay zero)."""
        m, d = self.model, self.data
        d.qpos[:] = q
        mujoco.mj_kinematics(m, d)
        if not jac:
            return None
        mujoco.mj_comPos(m, d)
        P = len(self.points)
        jp = np.zeros((P, 3, m.nv))
        jr = np.zeros((P, 3, m.nv))
        for i in range(self._n_closure_points if closure_only else P):
            mujoco.mj_jacSite(m, d, jp[i], jr[i], int(self.points[i]))
        return jp, jr

    def _closure(self, jp: np.ndarray | None, jr: np.ndarray | None, with_jac: bool = True):
        """Weighted closure residual (n_eq + springs,) and its Jacobian (.., nv) at the current kinematics of
        ``self.data`` (:meth:`_closure_rows` of one configuration)."""
        d = self.data
        sm = d.site_xmat[self.points].reshape(1, -1, 3, 3) if self._weld.any() else None
        r, J = self._closure_rows(d.site_xpos[self.points][None], sm, None if jp is None else jp[None],
                                  None if jr is None else jr[None], d.qpos[None], with_jac)
        return r[0], (J[0] if with_jac else None)

    def _closure_rows(self, sp, sm, jp, jr, qpos, with_jac: bool = True):
        """Weighted closure residuals (A, n_eq + springs) and Jacobians (A, .., nv) of A configurations
        from their point positions ``sp`` (A, npoints, 3), orientations ``sm`` (A, npoints, 3, 3; welds
        only), point Jacobians ``jp``, ``jr`` (A, npoints, 3, nv) and ``qpos`` (A, nq): rows
        ``sqrt(k) gap`` (unit weights without ``[closures]``) and ``sqrt(k_j) (q_j - ref_j)``."""
        A, nv = len(sp), self.model.nv
        r = self._gaps(sp, sm)
        J = [(jp[:, self._c1] - jp[:, self._c2]).reshape(A, -1, nv)] if with_jac else []
        if with_jac and self._weld.any():
            w1, w2 = self._c1[self._weld], self._c2[self._weld]
            J.append((jr[:, w1] - jr[:, w2]).reshape(A, -1, nv))
        r = r * self._sqrt_w
        if with_jac:
            J = np.concatenate(J, axis=1) * self._sqrt_w[:, None]
            keep = self._local_keep(J[..., self.passive])
            r, J = self._project(r, keep), self._project(J, keep)
        else:
            r, J = self._project(r, self._keep), None
        if len(self._spring_dof) or len(self._cpl_q1):
            rj, Jj = self._joint_rows(qpos, with_jac)
            r = np.concatenate([r, rj], axis=1)
            if with_jac:
                J = np.concatenate([J, Jj], axis=1)
        return r, J

    def _gaps(self, sp: np.ndarray, sm: np.ndarray | None) -> np.ndarray:
        """Closure gaps (A, n_eq), m and rad, unweighted: site1 - site2 positions of every closure, then the
        rotation errors of the welds, from point positions ``sp`` (A, npoints, 3) and orientations ``sm``."""
        r = [(sp[:, self._c1] - sp[:, self._c2]).reshape(len(sp), -1)]
        if self._weld.any():
            w1, w2 = self._c1[self._weld], self._c2[self._weld]
            r.append(_rotation_error(sm[:, w1].reshape(-1, 3, 3), sm[:, w2].reshape(-1, 3, 3)).reshape(len(sp), -1))
        return np.concatenate(r, axis=1)

    def _local_keep(self, Cp: np.ndarray) -> np.ndarray | None:
        """The projections (A, n_eq, n_eq) of the weighted closure rows off their redundant directions at A
        configurations, from the closure Jacobian's passive columns ``Cp`` (A, n_eq, npassive): the left
        singular directions of its ``len(redundant_directions)`` smallest singular values (the redundant
        directions found at ``home``, followed to this configuration and to these errors). None without
        redundancy or with ``[closures]`` compliance (:meth:`_read_redundancy`).

        Projecting at each configuration rather than with ``home``'s directions makes the assembly the
        joints' best closure wherever the machine is: the gap left is the part of the loop's misfit no joint
        motion changes (the part its play or strain takes). The identified errors tilt a planar loop's axes;
        home's directions then leave part of the gap to the joints at other poses, forward and inverse
        kinematics settle on two different compromises (ToddlerBot's neck: 0.005-0.015 deg apart, more than
        its calibration's predicted error) and the twin and a least-squares simulator disagree."""
        if self._keep is None:
            return None
        n_red = len(self.redundant_directions)
        ok = np.isfinite(Cp).all(axis=(1, 2))
        keep = np.broadcast_to(np.eye(Cp.shape[1]), (len(Cp),) + (Cp.shape[1],) * 2).copy()
        if ok.any():
            U = np.linalg.svd(Cp[ok], full_matrices=True)[0][..., -n_red:]          # (n, n_eq, n_red)
            keep[ok] -= U @ np.swapaxes(U, 1, 2)
        return keep

    @staticmethod
    def _project(rows: np.ndarray, keep: np.ndarray | None) -> np.ndarray:
        """Weighted closure rows (A, n_eq, ...) without their redundant directions: ``keep`` (n_eq, n_eq) or
        per configuration (A, n_eq, n_eq) (:meth:`_local_keep`); None leaves them."""
        if keep is None:
            return rows
        return np.einsum("ij,aj...->ai..." if keep.ndim == 2 else "aij,aj...->ai...", keep, rows)

    def _newton_batch(self, Q: np.ndarray, tol: np.ndarray, goals: np.ndarray | None = None) -> np.ndarray:
        """Assemble the configurations ``Q`` (A, nq) in place with the motor joints held (or, with task
        ``goals`` (A, C), every dof free and the task equations added: inverse kinematics): MuJoCo's
        kinematics per configuration, residuals and Newton steps vectorised (the same iteration as
        :meth:`_newton`). ``tol`` (A,) per configuration. Returns which converged."""
        m, d = self.model, self.data
        P = self._n_closure_points if goals is None else self.points.size
        nv = m.nv
        pts = [int(p) for p in self.points[:P]]
        weld = self._weld.any()
        rigid = self.spec.closures is None
        done = np.zeros(len(Q), bool)
        active = np.arange(len(Q))
        cols = self.passive if goals is None else np.arange(nv)
        tp = self._task_p
        need_jr = weld or (goals is not None and not all(c in POSITION for c in self.spec.task.coordinates))
        # residuals first, Jacobians only for the poses not yet met; not with redundant loops, whose residual
        # is projected with the Jacobian of each configuration (:meth:`_local_keep`)
        two_pass = rigid and goals is None and self._keep is None
        for _ in range(self.MAX_ITER):
            if not active.size:
                break
            if two_pass:
                # residuals first (kinematics only): the poses that already meet the tolerance need no
                # Jacobians (the last iteration of every pose)
                sp = np.empty((len(active), self.points.size, 3))
                sm = np.empty((len(active), self.points.size, 3, 3)) if weld else None
                for a, i in enumerate(active):
                    d.qpos[:] = Q[i]
                    mujoco.mj_kinematics(m, d)
                    sp[a] = d.site_xpos[self.points]
                    if weld:
                        sm[a] = d.site_xmat[self.points].reshape(-1, 3, 3)
                r, _ = self._closure_rows(sp, sm, None, None, Q[active], with_jac=False)
                met = np.max(np.abs(r), axis=1) < tol[active]
                done[active[met]] = True
                active = active[~met]
                if not active.size:
                    break
            A = len(active)
            sp = np.empty((A, self.points.size, 3))
            sm = np.empty((A, self.points.size, 3, 3)) if weld else None
            jp = np.zeros((A, self.points.size, 3, nv))
            jr = np.zeros((A, self.points.size, 3, nv)) if need_jr else None
            Rt = np.empty((A, 3, 3))
            for a, i in enumerate(active):
                d.qpos[:] = Q[i]
                mujoco.mj_kinematics(m, d)
                mujoco.mj_comPos(m, d)
                sp[a] = d.site_xpos[self.points]
                if weld:
                    sm[a] = d.site_xmat[self.points].reshape(-1, 3, 3)
                if goals is not None:
                    Rt[a] = d.site_xmat[self.task_site].reshape(3, 3)
                ja = jp[a]
                if need_jr:
                    jra = jr[a]
                    for k in range(P):
                        mujoco.mj_jacSite(m, d, ja[k], jra[k], pts[k])
                else:
                    for k in range(P):
                        mujoco.mj_jacSite(m, d, ja[k], None, pts[k])
            r, J = self._closure_rows(sp, sm, jp, jr, Q[active])
            if goals is not None:
                rt, Jt = self._task_rows_batch(sp[:, tp], Rt, jp[:, tp], None if jr is None else jr[:, tp],
                                               goals[active])
                r, J = np.concatenate([r, rt], axis=1), np.concatenate([J, Jt], axis=1)
            if rigid and not two_pass:
                met = np.max(np.abs(r), axis=1) < tol[active]
                done[active[met]] = True
                active, r, J = active[~met], r[~met], J[~met]
                if not active.size:
                    break
            Jc = J[:, :, cols]
            if Jc.shape[1] == Jc.shape[2]:
                step = -solve_stacked(Jc, r)
            elif goals is None:                           # least squares (compliant closures): normal eqs
                JT = np.swapaxes(Jc, 1, 2)
                step = -solve_stacked(JT @ Jc, (JT @ r[..., None])[..., 0])
            else:                                         # with the heavily weighted task rows: SVD
                step = -(np.linalg.pinv(Jc, rcond=1e-12) @ r[..., None])[..., 0]
            size = np.max(np.abs(step), axis=1)
            bad = ~np.isfinite(size)
            step *= np.minimum(1.0, self.MAX_STEP / np.where(bad, 1.0, np.maximum(size, 1e-300)))[:, None]
            dv = np.zeros(nv)
            for a, i in enumerate(active):
                if not bad[a]:
                    dv[cols] = step[a]
                    mujoco.mj_integratePos(m, Q[i], dv, 1.0)
            small = (size < tol[active]) & ~bad
            if not rigid:
                done[active[small]] = True               # stationary: the least-squares equilibrium
            active = active[~(bad | (small & (not rigid)))]
        return done

    #: Residual tolerance (m / rad) of the intermediate sub-steps of a continuation (the last is exact).
    PATH_TOL = 1e-7

    def _newton(self, q: np.ndarray, rows=None, tol: float | None = None) -> tuple[np.ndarray, bool]:
        """Assemble from ``q`` with the motor joints held (``rows`` None), or, for inverse kinematics, with
        every dof free and the extra equations ``rows(jp, jr) -> (residual, Jacobian)`` (the task);
        converged when the largest residual (rigid closures) or the largest step (compliant closures, whose
        least-squares equilibrium keeps a residual) is below ``tol`` (default :data:`TOL_M`)."""
        m = self.model
        q = q.copy()
        tol = self.TOL_M if tol is None else tol
        cols = self.passive if rows is None else np.arange(m.nv)
        for _ in range(self.MAX_ITER):
            jp, jr = self._kin(q, closure_only=rows is None)
            r, J = self._closure(jp, jr)
            if rows is not None:
                rt, Jt = rows(jp, jr)
                r, J = np.concatenate([r, rt]), np.vstack([J, Jt])
            if self.spec.closures is None and np.max(np.abs(r)) < tol:
                return q, True                             # rigid closures: met exactly
            step = -_least_squares_step(J[:, cols], r)
            size = np.max(np.abs(step))
            if not np.isfinite(size):
                return q, False
            if size < tol:                                 # stationary: the least-squares equilibrium
                dv = np.zeros(m.nv)
                dv[cols] = step
                mujoco.mj_integratePos(m, q, dv, 1.0)
                return q, True
            if size > self.MAX_STEP:
                step *= self.MAX_STEP / size
            dv = np.zeros(m.nv)
            dv[cols] = step
            mujoco.mj_integratePos(m, q, dv, 1.0)
        return q, False

    def _assemble(self, joints: np.ndarray, start: np.ndarray) -> tuple[np.ndarray, bool]:
        """Assemble at motor joint positions ``joints`` (M,) SI from configuration ``start`` by continuation:
        the motors move in sub-steps of at most :data:`PATH_STEP` of their range, each closed by Newton from
        the previous one (a long direct step can land on another assembly branch); the sub-steps halve
        when one fails."""
        j0 = start[self.motor_qadr].copy()
        span = (self.motor_range[:, 1] - self.motor_range[:, 0]) * self.motor_unit
        n = max(1, int(np.ceil(np.max(np.abs(joints - j0) / span) / self.PATH_STEP)))
        q = start
        for n_sub in (n, 4 * n):
            q, ok = start, True
            for t in np.linspace(0.0, 1.0, n_sub + 1)[1:]:
                q = q.copy()
                q[self.motor_qadr] = j0 + t * (joints - j0)
                q, ok = self._newton(q, tol=None if t == 1.0 else self.PATH_TOL)
                if not ok:
                    break
            if ok:
                return q, True
        return q, False

    # ------------------------------------------------------------------ public API
    def solve(self, commands, params: Mapping[str, float] | None = None) -> np.ndarray:
        """Assembled configurations (N, nq) at commands (N, M) (deg / mm) with errors ``params``.

        Each pose starts from the nearest configuration already assembled on this machine (``home`` or an
        earlier solve) and moves the motors there by continuation, in sub-steps of at most
        :data:`PATH_STEP` of the motor ranges, all poses together (:meth:`_newton_batch`); a pose that fails
        is redone alone in finer sub-steps from its nearest solved neighbour (:meth:`_assemble`). Every
        pose lies on the home branch. Rows that do not assemble (out of reach, singular) are NaN.
        """
        self.set_params(params)
        cmd = self._as_commands(commands)
        joints = self._joints_of(cmd)
        span = self.motor_range[:, 1] - self.motor_range[:, 0]
        known_cmd = np.concatenate([self.home_commands[None], self._warm_cmd])
        known_q = np.concatenate([self.home_qpos[None], self._warm_qpos])
        # All poses together: each from its nearest assembled configuration, by continuation in lockstep.
        # nearest known configuration in the largest motor move (a fraction of each range), by a k-d tree;
        # of equally near ones the oldest (home first): the same start for every solve of a pose, so
        # solves that differ only in the errors differ only by them (finite differences stay clean)
        start = np.zeros(len(cmd), int)
        near = np.zeros(len(cmd))
        finite = np.isfinite(cmd).all(axis=1)
        if finite.any():
            tree = cKDTree(known_cmd / span)
            x = cmd[finite] / span
            near[finite] = tree.query(x, p=np.inf)[0]
            start[finite] = [min(ball) for ball in tree.query_ball_point(x, near[finite] * (1 + 1e-12) + 1e-15,
                                                                        p=np.inf)]
        n_sub = np.maximum(1, np.ceil(near / self.PATH_STEP)).astype(int)
        Q = known_q[start].copy()
        j0 = Q[:, self.motor_qadr].copy()
        alive = np.isfinite(joints).all(axis=1)
        for step in range(1, int(n_sub.max(initial=0)) + 1):
            idx = np.flatnonzero(alive & (step <= n_sub))
            if not idx.size:
                continue
            t = (step / n_sub[idx])[:, None]
            Qi = Q[idx]
            Qi[:, self.motor_qadr] = j0[idx] + t * (joints[idx] - j0[idx])
            ok = self._newton_batch(Qi, np.where(step == n_sub[idx], self.TOL_M, self.PATH_TOL))
            Q[idx] = Qi
            alive[idx[~ok]] = False
        out = np.where(alive[:, None], Q, np.nan)
        # The poses that failed: one by one, from their nearest neighbour solved so far, in finer sub-steps.
        solved_cmd = np.concatenate([known_cmd, cmd[alive]])
        solved_q = np.concatenate([known_q, out[alive]])
        for i in np.flatnonzero(~alive & np.isfinite(joints).all(axis=1)):
            j = int(np.argmin(np.max(np.abs(solved_cmd - cmd[i]) / span, axis=1)))
            q, ok = self._assemble(joints[i], solved_q[j])
            if not ok and j != 0:
                q, ok = self._assemble(joints[i], self.home_qpos)
            if ok:
                out[i] = q
                solved_cmd = np.concatenate([solved_cmd, cmd[i][None]])
                solved_q = np.concatenate([solved_q, q[None]])
        good = np.isfinite(out).all(axis=1)
        if self.n_free and self.spec.closures is None and not any(dict(params or {}).values()):
            for i in np.flatnonzero(good):                # the nominal machine's: what base sets are made of
                out[i] = self._centre_free(out[i])
        self._remember(np.concatenate([self._warm_cmd, cmd[good]]), np.concatenate([self._warm_qpos, out[good]]))
        return out

    #: largest move (rad or m, in the passive dofs' tangent space) a free direction may keep from ``home``'s
    #: value after :meth:`_centre_free` (a spin 1e-9 rad off changes no derivative measurably), and its iterations
    CENTRE_TOL, CENTRE_ITER = 1e-9, 8

    def _free_directions(self, jp: np.ndarray, jr: np.ndarray) -> np.ndarray:
        """(npassive, nfree) orthonormal directions of the passive dofs the closures leave free at the
        configuration whose point Jacobians are ``jp``, ``jr`` (:meth:`_kin`): the closure Jacobian's null space
        (singular values below :data:`FREE_RTOL` of the largest)."""
        _, C = self._closure(jp, jr)
        _, sv, vt = np.linalg.svd(C[:, self.passive], full_matrices=True)
        rank = int(np.sum(sv > self.FREE_RTOL * max(sv.max(initial=0.0), 1e-30)))
        return vt[rank:].T

    def _centre_free(self, q: np.ndarray) -> np.ndarray:
        """``q`` (assembled) moved along the directions its closures leave free (a ball-ball rod's spin, an
        unactuated side chain: :meth:`_check_mobility`) to where they stand as at ``home``, and closed again:
        the configuration of the pose on the solution manifold whose free coordinates are home's, so a pose's
        configuration, and the derivatives taken there, do not depend on where its solve started. They did:
        a talos ankle rod's spin, carried from whichever earlier solve was nearest, changed a direction of the
        error Jacobian 500x (5e-6 against 6e-9 of the largest), and with it the base set (29 or 28 errors).
        Gauss-Newton on the free coordinates (their part of ``q - home``, :func:`mujoco.mj_differentiatePos`,
        in the closure Jacobian's null space); ``q`` unchanged where a step fails to close. Done on the nominal
        machine's solves (:meth:`solve` with no errors), whose derivatives make the base sets and plans: on a
        machine with errors the free coordinates stay where the solve left them (a fit's iterations would pay
        for it, 3 of wl16's 6 s, and their derivatives along a free spin differ by 1e-6 of the largest)."""
        m = self.model
        d = np.zeros(m.nv)
        for _ in range(self.CENTRE_ITER):
            free = self._free_directions(*self._kin(q, closure_only=True))
            mujoco.mj_differentiatePos(m, d, 1.0, self.home_qpos, q)
            off = free.T @ d[self.passive]
            if not off.size or np.max(np.abs(off)) < self.CENTRE_TOL:
                break
            dv = np.zeros(m.nv)
            dv[self.passive] = -free @ off
            moved = q.copy()
            mujoco.mj_integratePos(m, moved, dv, 1.0)
            moved, ok = self._newton(moved)
            if not ok:
                break
            q = moved
        return q

    def _remember(self, cmd: np.ndarray, qpos: np.ndarray) -> None:
        """Keep assembled configurations (latest last, at most 4096) as warm starts of later solves."""
        self._warm_cmd = cmd[-4096:]
        self._warm_qpos = qpos[-4096:]

    def kinematics(self, qpos: np.ndarray) -> Kinematics:
        """World poses and point Jacobians (:class:`Kinematics`) at configurations ``qpos`` (N, nq), SI."""
        m, d = self.model, self.data
        qpos = np.atleast_2d(qpos)
        N, P = len(qpos), len(self.points)
        out = Kinematics(qpos=qpos, xpos=np.full((N, m.nbody, 3), np.nan), xmat=np.full((N, m.nbody, 3, 3), np.nan),
                         site_xpos=np.full((N, P, 3), np.nan), site_xmat=np.full((N, P, 3, 3), np.nan),
                         jacp=np.full((N, P, 3, m.nv), np.nan), jacr=np.full((N, P, 3, m.nv), np.nan))
        for i in range(N):
            if not np.isfinite(qpos[i]).all():
                continue
            out.jacp[i], out.jacr[i] = self._kin(qpos[i])
            out.xpos[i] = d.xpos
            out.xmat[i] = d.xmat.reshape(-1, 3, 3)
            out.site_xpos[i] = d.site_xpos[self.points]
            out.site_xmat[i] = d.site_xmat[self.points].reshape(-1, 3, 3)
        return out

    def targets(self, commands, params: Mapping[str, float] | None = None) -> np.ndarray:
        """Tracker nest positions (N, K, 3) mm, world frame; NaN rows where the chain cannot assemble."""
        qpos = self.solve(commands, params)
        return self._sites_mm(qpos, self.target_sites)

    def observe_at(self, qpos: np.ndarray) -> np.ndarray:
        """:meth:`observe` at assembled configurations ``qpos`` (N, nq) (a :meth:`solve`'s): (N, R) mm."""
        return self._observed(self._sites_mm(qpos, self.target_sites))

    def _sites_mm(self, qpos: np.ndarray, sites: np.ndarray) -> np.ndarray:
        out = np.full((len(qpos), len(sites), 3), np.nan)
        for i, q in enumerate(qpos):
            if np.isfinite(q).all():
                self._kin(q, jac=False)
                out[i] = self.data.site_xpos[sites] / MM
        return out

    def measure(self, commands, params: Mapping[str, float] | None = None,
                rng: np.random.Generator | None = None, sigma: float | None = None) -> np.ndarray:
        """A tracker reading (N, K, 3) mm: :meth:`targets` plus Gaussian noise of ``sigma`` mm per coordinate
        (default the machine's ``sigma_mm``) drawn from ``rng``."""
        rng = rng if rng is not None else np.random.default_rng()
        y = self.targets(commands, params)
        return y + rng.normal(0.0, self.sigma_mm if sigma is None else sigma, y.shape)

    def jacobian(self, commands, params: Mapping[str, float] | None = None,
                 keys: list[str] | None = None) -> np.ndarray:
        """Exact d targets / d errors (N, K, 3, P) at commands (N, M), mm per key unit (mm/mm, mm/deg),
        by the implicit-function theorem (module docstring). ``keys`` default :attr:`error_keys`. NaN rows
        where the chain cannot assemble."""
        kin, dpos, _ = self._point_jacobians(commands, params, keys)
        return dpos[:, self._tp] / MM

    # ------------------------------------------------------------------ observations (what is read of a pose)
    @property
    def reading_reference(self) -> str | None:
        """``[tracker] reference`` of a ``"distance"`` measurement (``"previous"`` / ``"first"``), else None:
        identification then fits scale readings (:func:`pmcal.calib.closed_chain.reading_operator`)."""
        return self.spec.reference if self.spec.measure == "distance" else None

    @property
    def n_observed(self) -> int:
        """Values read of each pose: 3 K nest coordinates, or 1 distance (``measure = "distance"``)."""
        return 1 if self.spec.measure == "distance" else 3 * self.n_targets

    def observe(self, commands, params: Mapping[str, float] | None = None) -> np.ndarray:
        """What the tracker reads of each pose, before a reference is taken off: (N, R) mm. ``"position"``
        and ``"pose"``: the nest coordinates ``t1_x .. tK_z`` (R = 3 K, world frame); ``"distance"``: the
        distance between the two target sites (R = 1; the scale reads its change relative to a reference
        pose, :func:`pmcal.calib.closed_chain.reading_operator`). NaN rows where the chain cannot assemble."""
        y = self.targets(commands, params)
        return self._observed(y)

    def _observed(self, y: np.ndarray) -> np.ndarray:
        if self.spec.measure == "distance":
            return np.linalg.norm(y[:, 1] - y[:, 0], axis=1)[:, None]
        return y.reshape(len(y), -1)

    def observation_jacobian(self, commands, params: Mapping[str, float] | None = None,
                             keys: list[str] | None = None) -> np.ndarray:
        """Exact d :meth:`observe` / d errors (N, R, P), mm per key unit (IFT, module docstring): for a
        distance ``|b - a|`` the unit vector from a to b times the difference of the two sites' derivatives."""
        kin, dpos, _ = self._point_jacobians(commands, params, keys)
        J = dpos[:, self._tp] / MM                                        # (N, K, 3, P)
        if self.spec.measure != "distance":
            return J.reshape(len(J), -1, J.shape[-1])
        v = kin.site_xpos[:, self._tp[1]] - kin.site_xpos[:, self._tp[0]]
        u = v / np.linalg.norm(v, axis=1, keepdims=True)
        return np.einsum("nc,ncp->np", u, J[:, 1] - J[:, 0])[:, None, :]

    def task_jacobian(self, commands, params: Mapping[str, float] | None = None,
                      keys: list[str] | None = None) -> np.ndarray:
        """Exact d task coordinates / d errors (N, C, P) at fixed commands (N, M): how far each error moves
        the task site, in the coordinates' units (mm, deg) per key unit. ``J Cov J^T`` is the task-space
        covariance a compensation with identified errors of covariance ``Cov`` leaves."""
        kin, dpos, drot = self._point_jacobians(commands, params, keys)
        coords = self.spec.task.coordinates
        out = np.full((len(kin.qpos), len(coords), dpos.shape[-1]), np.nan)
        tp = self._task_p
        Rf = self._frame_R.T
        for i, c in enumerate(coords):
            if c in POSITION:
                out[:, i] = (Rf @ dpos[:, tp])[:, POSITION.index(c)] / MM
        ang = [i for i, c in enumerate(coords) if c not in POSITION]
        if ang:
            for n in range(len(kin.qpos)):
                if np.isfinite(kin.qpos[n]).all():
                    p, R = self._in_task_frame(kin.site_xpos[n, tp], kin.site_xmat[n, tp])
                    D = self._angle_rates(p / MM, R)
                    out[n, ang] = D @ Rf @ drot[n, tp]
        return out

    def body_bounds_mm(self, body: int) -> tuple[np.ndarray, np.ndarray]:
        """The bounding box (lo, hi) (3,) mm in ``body``'s frame of its geoms (meshes included), or of its
        sites widened by 10 mm when it has no geom: where a tracker nest can sit on it."""
        m = self.model
        corners = []
        for g in np.flatnonzero(m.geom_bodyid == body):
            R = np.empty(9)
            mujoco.mju_quat2Mat(R, m.geom_quat[g])
            half = m.geom_aabb[g, 3:]
            box = m.geom_aabb[g, :3] + np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * half
            corners.append(m.geom_pos[g] + box @ R.reshape(3, 3).T)
        if not corners:
            pts = m.site_pos[m.site_bodyid == body]
            return pts.min(0) / MM - 10.0, pts.max(0) / MM + 10.0
        pts = np.vstack(corners)
        return pts.min(0) / MM, pts.max(0) / MM

    def body_point_jacobian(self, commands, body: int, points_mm: np.ndarray,
                            params: Mapping[str, float] | None = None, keys: list[str] | None = None) -> np.ndarray:
        """Exact d position / d errors (N, Q, 3, P), mm per key unit, world frame, of points fixed on ``body``
        (a body id carrying one of the twin's sites: a tracker target, a closure site or the task site) at
        ``points_mm`` (Q, 3) mm in the body's frame: where a tracker nest mounted there would move. A rigid
        body's field, ``d x_p = d x_s + d w x (x_p - x_s)``, from a site ``s`` on it (:meth:`jacobian`'s
        derivatives). NaN rows where the chain cannot assemble."""
        on = [i for i, s in enumerate(self.points) if self.model.site_bodyid[s] == body]
        if not on:
            raise ValueError(f"body {body} carries none of the twin's sites")
        kin, dpos, drot = self._point_jacobians(commands, params, keys)
        i = on[0]
        x = kin.xpos[:, body, None] + np.einsum("nab,qb->nqa", kin.xmat[:, body], np.asarray(points_mm) * MM)
        r = x - kin.site_xpos[:, i, None]                                          # (N, Q, 3) m
        return (dpos[:, i, None] + np.cross(drot[:, i, None], r[..., None], axis=2)) / MM

    def _point_jacobians(self, commands, params, keys):
        """Kinematics at the assembled commands and the total derivatives (N, npoints, 3, P) of every
        point's position (m) and orientation (rad) per key unit: the IFT of the module docstring."""
        keys = list(keys or self.error_keys)
        idx = [self.errors.index(k) for k in keys]
        kin = self.kinematics(self.solve(commands, params))
        dP, dW = self.errors.derivatives(kin, idx)                     # (N, npts, 3, P) SI
        N, nv = len(kin.qpos), self.model.nv
        C, Ce = self._closure_columns(kin, dP, dW)
        strain = self._strain_terms(kin, C, idx)
        keep = self._local_keep(C[..., self.passive])
        C, Ce = self._project(C, keep), self._project(Ce, keep)
        if len(self._spring_dof) or len(self._cpl_q1):                    # joint springs and equalities
            Cs = np.zeros((N, len(self._spring_dof) + len(self._cpl_q1), nv))
            ok = np.isfinite(kin.qpos).all(axis=1)
            Cs[ok] = self._joint_rows(kin.qpos[ok])[1]
            Ces = np.zeros(Cs.shape[:2] + (len(keys),))
            for c, dof, unit in self.errors.zero_columns(idx):          # a geared motor's offset moves its pair
                Ces[..., c] = Cs[..., dof] * unit
            C, Ce = np.concatenate([C, Cs], axis=1), np.concatenate([Ce, Ces], axis=1)
        dpos = np.full(dP.shape, np.nan)
        drot = np.full(dW.shape, np.nan)
        ok = np.isfinite(kin.qpos).all(axis=1)
        if ok.any():
            Cp, Cep = C[ok][:, :, self.passive], Ce[ok]
            if strain is None:
                dq = -np.linalg.pinv(Cp, rcond=1e-10) @ Cep                 # (n, npassive, P)
            else:                                                        # the loops keep a gap
                CpT = np.swapaxes(Cp, 1, 2)
                dq = -solve_stacked(CpT @ Cp + strain[0][ok], CpT @ Cep + strain[1][ok])
                bad = ~np.isfinite(dq).all(axis=(1, 2))                 # singular there: the Gauss-Newton part
                dq[bad] = -np.linalg.pinv(Cp[bad], rcond=1e-10) @ Cep[bad]
            dpos[ok] = np.einsum("nkcv,nvp->nkcp", kin.jacp[ok][..., self.passive], dq) + dP[ok]
            drot[ok] = np.einsum("nkcv,nvp->nkcp", kin.jacr[ok][..., self.passive], dq) + dW[ok]
        return kin, dpos, drot

    def _closure_columns(self, kin: Kinematics, dP: np.ndarray, dW: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The weighted closure rows' derivatives at configurations ``kin``, not projected: by the dofs
        (N, n_eq, nv) and by the errors (N, n_eq, P) whose point derivatives are ``dP``, ``dW``."""
        N, nv = len(kin.qpos), self.model.nv
        C = np.concatenate([kin.jacp[:, self._c1] - kin.jacp[:, self._c2],
                            kin.jacr[:, self._c1[self._weld]] - kin.jacr[:, self._c2[self._weld]]],
                           axis=1).reshape(N, -1, nv)
        Ce = np.concatenate([dP[:, self._c1] - dP[:, self._c2],
                             dW[:, self._c1[self._weld]] - dW[:, self._c2[self._weld]]],
                            axis=1).reshape(N, -1, dP.shape[-1])
        return C * self._sqrt_w[:, None], Ce * self._sqrt_w[:, None]

    #: closure gap (m, rad) above which a loop counts as strained (:meth:`_strain_terms`), and the step (rad or
    #: m per passive dof) of the finite differences of the closure rows' derivatives there
    STRAIN_GAP, STRAIN_STEP = 1e-9, 1e-6

    def _strain_terms(self, kin: Kinematics, C: np.ndarray, idx: list[int]):
        """Second-order terms of the assembly's derivative where the loops keep a gap (conflicting closures:
        closed along their independent directions, or compliant), else None.

        The assembly then meets ``C_p^T c = 0`` (the joints' best closure: the gap ``c`` left is what no
        passive joint motion changes) rather than ``c = 0``, and its derivative by the errors is
        ``dq_p/dp = -(C_p^T C_p + R_q)^-1 (C_p^T C_e + R_p)`` with ``R_q = d(C_p^T c)/dq_p`` and ``R_p =
        d(C_e^T c)/dq_p^T`` at ``c`` held (``sum_i c_i d2 c_i / dq dp``: the mixed second derivatives are
        symmetric), by central differences of MuJoCo's Jacobians and the errors' closed-form derivatives over
        the passive dofs. Their size is the gap's: a strained planar loop's out-of-plane tilts move its
        nests through them as much as through the Gauss-Newton part (docs/closed_chain.md, "Derivatives").
        Returns (R_q (N, np, np), R_p (N, np, P)); needs no free passive direction (else None)."""
        if (self._keep is None and self.spec.closures is None) or self.n_free:
            return None
        ok = np.isfinite(kin.qpos).all(axis=1)
        sm = kin.site_xmat if self._weld.any() else None
        raw = self._gaps(kin.site_xpos[ok], None if sm is None else sm[ok])          # m, rad
        if not raw.size or np.max(np.abs(raw)) < self.STRAIN_GAP:
            return None
        gap = np.zeros((len(kin.qpos), C.shape[1]))
        gap[ok] = raw * self._sqrt_w
        m, h, npas = self.model, self.STRAIN_STEP, len(self.passive)
        Rq, Rp = np.zeros((len(gap), npas, npas)), np.zeros((len(gap), npas, len(idx)))
        # poses a chunk: the error derivatives of 2 * np moved configurations per pose, at most ~4e6 numbers
        chunk = max(1, int(4e6 // (2 * npas * len(self.points) * 3 * max(len(idx), 1))))
        for lo in range(0, len(gap), chunk):
            part = slice(lo, min(lo + chunk, len(gap)))
            Q = np.repeat(kin.qpos[part], 2 * npas, axis=0)              # (n * np * 2, nq): + then - per dof
            for row in np.flatnonzero(np.repeat(ok[part], 2 * npas)):
                dv = np.zeros(m.nv)
                dv[self.passive[(row // 2) % npas]] = h if row % 2 == 0 else -h
                mujoco.mj_integratePos(m, Q[row], dv, 1.0)
            moved = self.kinematics(Q)
            Cm, Cem = self._closure_columns(moved, *self.errors.derivatives(moved, idx))
            g = np.repeat(gap[part], 2 * npas, axis=0)[..., None]        # the gap held
            Gq = np.sum(Cm[..., self.passive] * g, axis=1).reshape(-1, npas, 2, npas)
            Ge = np.sum(Cem * g, axis=1).reshape(-1, npas, 2, len(idx))
            Rq[part] = (Gq[:, :, 0] - Gq[:, :, 1]) / (2 * h)             # [n, j, l] = d(C_p^T c)_l / dq_j
            Rp[part] = (Ge[:, :, 0] - Ge[:, :, 1]) / (2 * h)             # [n, j, k] = d(C_e^T c)_k / dq_j
        Rq = 0.5 * (Rq + np.swapaxes(Rq, 1, 2))                          # a Hessian: symmetric
        return np.where(ok[:, None, None], Rq, 0.0), np.where(ok[:, None, None], Rp, 0.0)

    # ------------------------------------------------------------------ task space
    def targets_in_task_frame(self, params: Mapping[str, float] | None = None) -> np.ndarray:
        """The nests' coordinates (K, 3) mm in the task site's frame at ``home`` (rigid on the same part:
        the same everywhere). With ``measure = "pose"`` a tracker reading ``Y`` (N, K, 3) gives the task
        frame's pose by ``pmcal.mechanism.rigid.fit_pose(Y, twin.targets_in_task_frame())``."""
        self.set_params(params)
        self._kin(self.solve(self.home_commands[None])[0], jac=False)
        d = self.data
        R = d.site_xmat[self.task_site].reshape(3, 3)
        return (d.site_xpos[self.target_sites] - d.site_xpos[self.task_site]) @ R / MM

    @property
    def reading_fixes_task(self) -> bool:
        """A tracker reading fixes the task site (:meth:`task_from_reading`): 3 or more nests measured in
        position, all on the task site's body."""
        body = self.model.site_bodyid
        return (self.spec.measure != "distance" and self.n_targets >= 3
                and bool(np.all(body[self.target_sites] == body[self.task_site])))

    def task_from_reading(self, Y: np.ndarray) -> np.ndarray:
        """Task coordinates (N, C) of the task site as a tracker reading ``Y`` (N, K, 3) mm of the nests gives
        them: the rigid fit (:func:`pmcal.mechanism.rigid.fit_pose`) of the nests' coordinates in the task
        site's frame (:meth:`targets_in_task_frame` of the nominal machine: nests and task site carry no
        errors, they define their part) to ``Y``, written in the task frame. Needs 3 or more nests on the
        task site's body (ValueError otherwise: the reading does not fix the task site)."""
        if not self.reading_fixes_task:
            raise ValueError(f"the tracker's reading of {self.spec.name} does not fix its task site: that takes 3 "
                             "or more nests on the task site's part")
        r, R, _ = fit_pose(Y, self.targets_in_task_frame())
        p, R = self._in_task_frame(r * MM, R)
        return task_coordinates(p / MM, R, self.spec.task.coordinates)

    def task_of(self, qpos: np.ndarray) -> np.ndarray:
        """Task coordinates (N, C) of configurations ``qpos`` (N, nq); NaN rows stay NaN."""
        coords = self.spec.task.coordinates
        out = np.full((len(qpos), len(coords)), np.nan)
        for i, q in enumerate(qpos):
            if np.isfinite(q).all():
                self._kin(q, jac=False)
                p, R = self._in_task_frame(self.data.site_xpos[self.task_site],
                                           self.data.site_xmat[self.task_site].reshape(3, 3))
                out[i] = task_coordinates(p[None] / MM, R[None], coords)[0]
        return out

    def forward(self, commands, params: Mapping[str, float] | None = None) -> np.ndarray:
        """Task coordinates (N, C) reached at commands (N, M) (forward kinematics); NaN where the chain
        cannot assemble."""
        return self.task_of(self.solve(commands, params))

    def _angle_rates(self, p_mm: np.ndarray, R: np.ndarray) -> np.ndarray:
        """d (angle task coordinates, deg) / d (world rotation vector of the task frame, rad), (..., C_ang,
        3) at positions ``p_mm`` (..., 3) and orientations ``R`` (..., 3, 3): central differences of the
        closed-form angles of ``R`` (not of the chain), step 1e-7 rad."""
        coords = self.spec.task.coordinates
        ang = [i for i, c in enumerate(coords) if c not in POSITION]
        h = 1e-7
        turns = rotvec_matrix(np.concatenate([np.eye(3), -np.eye(3)]) * h) @ R[..., None, :, :]   # (..., 6, 3, 3)
        t = task_coordinates(np.broadcast_to(p_mm[..., None, :], turns.shape[:-1]), turns, coords)
        return np.swapaxes(task_difference(t[..., :3, :], t[..., 3:, :], coords)[..., ang] / (2 * h), -1, -2)

    def _task_rows_batch(self, p_m: np.ndarray, R: np.ndarray, jp: np.ndarray, jr: np.ndarray,
                         goals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Weighted task equations of A configurations: residuals (A, C) (m, rad) and Jacobians (A, C, nv)
        from the task site's position ``p_m`` (A, 3) m, orientation ``R`` (A, 3, 3) and Jacobians ``jp``,
        ``jr`` (A, 3, nv), towards ``goals`` (A, C) (task units)."""
        coords = self.spec.task.coordinates
        is_pos = np.array([c in POSITION for c in coords])
        p_m, R = self._in_task_frame(p_m, R)
        jp = self._frame_R.T @ jp
        jr = None if jr is None else self._frame_R.T @ jr
        now = task_coordinates(p_m / MM, R, coords)
        diff = task_difference(now, goals, coords)
        r = np.where(is_pos, diff * MM, diff * DEG)
        J = np.zeros((len(p_m), len(coords), self.model.nv))
        for i, c in enumerate(coords):
            if c in POSITION:
                J[:, i] = jp[:, POSITION.index(c)]
        if not is_pos.all():
            J[:, ~is_pos] = self._angle_rates(p_m / MM, R) * DEG @ jr
        return r * self._task_sqrt_w, J * self._task_sqrt_w

    def _task_rows(self, goal: np.ndarray):
        """Task equations for :meth:`_newton`: residual (C,) (m, rad) and Jacobian (C, nv)."""
        d, tp = self.data, self._task_p

        def rows(jp, jr):
            R = d.site_xmat[self.task_site].reshape(1, 3, 3)
            r, J = self._task_rows_batch(d.site_xpos[self.task_site][None], R, jp[tp][None], jr[tp][None],
                                         goal[None])
            return r[0], J[0]

        return rows

    def inverse_report(self, task, params: Mapping[str, float] | None = None) -> tuple[np.ndarray, list[str]]:
        """:meth:`inverse` with the reason for each NaN row (``""`` where reached)."""
        self.set_params(params)
        coords = self.spec.task.coordinates
        task = np.atleast_2d(np.asarray(task, float))
        if task.shape[-1] != len(coords):
            raise ValueError(f"task needs {len(coords)} columns ({', '.join(coords)}), got shape {task.shape}")
        home_task = self.task_of(self.home_qpos[None])[0]
        cmd = np.full((len(task), self.n_motors), np.nan)
        reasons = [""] * len(task)
        width = np.array([self.spec.workspace[c][1] - self.spec.workspace[c][0] for c in coords])
        # All targets together, each from the nearest assembled configuration (home, or one of earlier
        # solves: all on the home branch) along a straight task path (lockstep continuation); the ones that
        # fail are redone one by one from the nearest target reached, in finer sub-steps.
        known_q = np.concatenate([self.home_qpos[None], self._warm_qpos[-512:]])
        known_t = np.concatenate([home_task[None], self.task_of(known_q[1:])])
        alive = np.isfinite(task).all(axis=1)
        dist = np.array([np.max(np.abs(task_difference(t, known_t, coords)) / width, axis=1) if ok else
                         np.zeros(len(known_t)) for t, ok in zip(task, alive)]).reshape(len(task), len(known_t))
        dist[~np.isfinite(dist)] = np.inf
        dist[:, 0] = np.where(np.isfinite(dist[:, 0]), dist[:, 0], 0.0)
        start = np.argmin(dist, axis=1)
        start_task = known_t[start]
        delta = task_difference(task, start_task, coords)
        gap = dist[np.arange(len(task)), start]
        far = alive & (gap > self.MAX_PATH_BOXES)
        alive &= ~far
        n_sub = np.maximum(1, np.ceil(np.where(far, 0.0, gap) / self.PATH_STEP)).astype(int)
        Q = known_q[start].copy()
        for step in range(1, int(n_sub[alive].max(initial=0)) + 1):
            idx = np.flatnonzero(alive & (step <= n_sub))
            if not idx.size:
                continue
            goals = start_task[idx] + (step / n_sub[idx])[:, None] * delta[idx]
            Qi = Q[idx]
            ok = self._newton_batch(Qi, np.where(step == n_sub[idx], self.TOL_M, self.PATH_TOL), goals)
            Q[idx] = Qi
            alive[idx[~ok]] = False
        known_task = [home_task] + list(task[alive])
        known_q = [self.home_qpos] + list(Q[alive])         # for the fallback: home and the targets reached
        for i, goal in enumerate(task):
            if alive[i]:
                q, ok = Q[i], True
            elif not np.isfinite(goal).all() or far[i]:
                q, ok = self.home_qpos, False
            else:
                dist = np.max(np.abs(task_difference(goal, np.array(known_task), coords)) / width, axis=1)
                j = int(np.argmin(dist))
                q, ok = self._reach_task(goal, known_task[j], known_q[j], dist[j])
                if not ok and j != 0:
                    q, ok = self._reach_task(goal, home_task, self.home_qpos, dist[0])
            if not ok:
                reasons[i] = ("the target has missing (NaN) coordinates" if not np.isfinite(goal).all() else
                              f"the target is {gap[i]:.3g} [workspace] box sizes from every assembled pose "
                              "(out of reach; a box in metres?)" if far[i] else
                              "no assembly of the chain reaches this target (out of the workspace or singular)")
                continue
            if not alive[i]:
                known_task.append(goal)
                known_q.append(q)
            c = self._commands_of(q[None])[0]
            lo, hi = self.motor_range[:, 0], self.motor_range[:, 1]
            out = np.flatnonzero((c < lo) | (c > hi))
            if out.size:
                j = out[0]
                mot = self.spec.motors[j]
                reasons[i] = (f"{mot.name} (joint {mot.joint}) command {c[j]:.3f} {mot.unit} outside its range "
                              f"[{lo[j]:g}, {hi[j]:g}]")
                continue
            cmd[i] = c
            self._remember(np.concatenate([self._warm_cmd, c[None]]), np.concatenate([self._warm_qpos, q[None]]))
        return cmd, reasons

    def _reach_task(self, goal: np.ndarray, start_task: np.ndarray, start_q: np.ndarray, dist: float):
        """Configuration reaching task coordinates ``goal`` from an assembled ``start_q`` (at
        ``start_task``) by continuation along the straight task-space path, in sub-steps of at most
        :data:`PATH_STEP` of the workspace box (``dist``: the whole path in those units)."""
        coords = self.spec.task.coordinates
        n = max(1, int(np.ceil(dist / self.PATH_STEP)))
        q, ok = start_q, False
        for n_sub in (n, 4 * n):
            q, ok = start_q, True
            for t in np.linspace(0.0, 1.0, n_sub + 1)[1:]:
                sub = start_task + t * task_difference(goal, start_task, coords)
                q, ok = self._newton(q, rows=self._task_rows(sub), tol=None if t == 1.0 else self.PATH_TOL)
                if not ok:
                    break
            if ok:
                break
        return q, ok

    def inverse(self, task, params: Mapping[str, float] | None = None) -> np.ndarray:
        """Commands (N, M) (deg / mm) that put the task site at ``task`` (N, C) (coordinates of
        ``spec.task``, mm / deg) on the machine with errors ``params``: Newton on the closure and task
        equations together, by continuation along the straight task path from the nearest assembled
        configuration (``home`` or a recent solve), all targets at once (:meth:`_newton_batch`); a target
        that fails is redone alone in finer sub-steps from the nearest one reached. Every solution lies on
        the home branch. NaN rows
        where out of reach or outside a motor's range (:meth:`inverse_report` says which)."""
        return self.inverse_report(task, params)[0]

    def sample_task(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` task points (n, C) drawn uniformly from the workspace box of the machine.toml."""
        box = np.array([self.spec.workspace[c] for c in self.spec.task.coordinates])
        return rng.uniform(box[:, 0], box[:, 1], size=(n, len(box)))

    def sample_commands(self, n: int, rng: np.random.Generator, params: Mapping[str, float] | None = None,
                        max_rounds: int = 20) -> np.ndarray:
        """``n`` commands (n, M) whose poses are uniform over the workspace box, filtered by reach and motor
        ranges (the inverse kinematics of the machine with ``params``, default nominal)."""
        got: list[np.ndarray] = []
        count, drawn, why = 0, 0, ""
        for _ in range(max_rounds):
            cmd, reasons = self.inverse_report(self.sample_task(max(2 * (n - count), 4), rng), params)
            drawn += len(reasons)
            why = why or next((r for r in reasons if r), "")
            cmd = cmd[np.isfinite(cmd).all(axis=1)]
            got.append(cmd)
            count += len(cmd)
            if count >= n:
                return np.concatenate(got)[:n]
            if count == 0 and drawn >= self.HOPELESS_DRAWS:
                break
        raise InputError(f"only {count} of {n} poses drawn from [workspace] are reachable within the motor ranges "
                         f"({drawn} drawn; e.g. {why}): check [workspace] and [[motors]] range and zero",
                         file=str(self.spec.folder / "machine.toml"), field="workspace")


def _least_squares_step(J: np.ndarray, r: np.ndarray) -> np.ndarray:
    """``x`` minimising ``|J x - r|`` (minimum norm): LU for a regular square ``J``, else SVD."""
    if J.shape[0] == J.shape[1]:
        try:
            x = np.linalg.solve(J, r)
            if np.all(np.isfinite(x)):
                return x
        except np.linalg.LinAlgError:
            pass
    return np.linalg.lstsq(J, r, rcond=1e-12)[0]


def _rotation_error(R1: np.ndarray, R2: np.ndarray) -> np.ndarray:
    """Rotation vectors (n, 3) rad of ``R1 R2^T`` (world frame): the weld residual, zero when aligned."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R1 @ np.swapaxes(R2, -1, -2)).as_rotvec().reshape(-1, 3)
