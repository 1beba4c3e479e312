"""Dynamic simulation of the twin: gravity, position servos on the motors, settling.

The quasi-static twin (:mod:`pmcal.twin.ocpm.assembly`) puts explicit stiffness on every closure. The dynamic model
keeps the same physics where it matters and stays integrable with an ordinary time step:

- passive closures (limbs 3, 4): explicit spring-dampers of the configured stiffness, applied at the
  sites as generalised forces ``-J^T (k gap + c d(gap)/dt)`` each step;
- actuated closures (limbs 1, 2) and the SS limb's axial spring: hard equality constraints (the limit of
  a stiffness ratio -> infinity; at the reference ratio 1000 the difference is ~1e-3 of the misfit);
- motors: MuJoCo position actuators (``kp``, ``kv``), so a gravity load makes them sag by ``tau / kp``;
- gravity from the inertia of machine.toml, plus an optional payload at the platform centre.

Use it for settling behaviour and for effects that need dynamics; campaigns use the quasi-static twin.
Units: SI inside, mm/deg at the interface (as :class:`pmcal.twin.ocpm.machine.TwinState`).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import mujoco
import numpy as np

from pmcal.twin.ocpm.machine import Twin, TwinState
from pmcal.twin.ocpm.model import MM


@dataclass
class SettleInfo:
    time: float            # simulated seconds until settled (or the limit)
    settled: bool
    max_speed: float       # largest joint speed at the end, rad/s or m/s


class DynamicTwin:
    """Time-domain simulation of a :class:`Twin` (same geometry and errors)."""

    def __init__(self, twin: Twin, timestep: float = 1e-4, servo_kp: float = 2e5, servo_kv: float = 2e3,
                 damping_ratio: float = 0.7, payload_kg: float = 0.0):
        self.twin = twin
        m = copy.copy(twin.model)
        m.opt.disableflags = 0               # the twin's own model is set up for kinematics only
        m.opt.timestep = timestep
        # Euler (implicit joint damping) is stable with stiff servos and hard equalities; implicitfast
        # oscillates or diverges with that combination (tried on this model).
        m.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
        idx = twin.index
        passive = [j for j in range(len(idx.site_s1)) if (j + 1) not in twin.geom.actuated]
        self.passive = np.array(passive, dtype=int)
        m.eq_active0[:] = 1
        # Hard constraints: the stiffest setting the time step allows (solref >= 2 dt).
        m.eq_solref[:] = [2.0 * timestep, 1.0]
        m.eq_solimp[:] = [0.9999, 0.99999, 0.001, 0.5, 2.0]
        m.eq_active0[idx.eq_closure[self.passive]] = 0
        m.jnt_stiffness[idx.jnt_slide] = 0.0
        for a in range(m.nu):
            m.actuator_gainprm[a, 0] = servo_kp
            m.actuator_biasprm[a, 1:3] = [-servo_kp, -servo_kv]
        self.payload_kg = float(payload_kg)
        m.body_mass[idx.platform] += self.payload_kg
        self.m = m
        self.d = mujoco.MjData(m)
        self.k = np.asarray(twin.stiffness.closure, float)[self.passive]
        link_mass = twin.geom.link_mass
        self.c = 2.0 * damping_ratio * np.sqrt(self.k * link_mass)
        self._jp1, self._jp2 = np.zeros((3, m.nv)), np.zeros((3, m.nv))

    def _closure_forces(self) -> None:
        m, d, idx = self.m, self.d, self.twin.index
        d.qfrc_applied[:] = 0.0
        for k, c, j in zip(self.k, self.c, self.passive):
            mujoco.mj_jacSite(m, d, self._jp1, None, idx.site_s1[j])
            mujoco.mj_jacSite(m, d, self._jp2, None, idx.site_s2[j])
            J = self._jp1 - self._jp2
            gap = d.site_xpos[idx.site_s1[j]] - d.site_xpos[idx.site_s2[j]]
            d.qfrc_applied -= J.T @ (k * gap + c * (J @ d.qvel))

    def settle(self, m_cmd_deg: np.ndarray, duration: float = 1.0, speed_tol: float = 1e-7) -> tuple[TwinState, SettleInfo]:
        """Start from the quasi-static pose of the command, run until joint speeds fall below ``speed_tol``."""
        m, d, twin = self.m, self.d, self.twin
        joint = np.deg2rad(np.asarray(m_cmd_deg, float).reshape(1, 2)) + twin.errors.dtheta[:2]
        start = twin.reach_joint(joint)
        mujoco.mj_resetData(m, d)
        d.qpos[:] = start.qpos[0]
        d.qpos[twin.index.qadr_slide] = 0.0
        d.ctrl[:] = joint[0]
        n_steps = int(round(duration / m.opt.timestep))
        settled, step = False, 0
        for step in range(1, n_steps + 1):
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
            self._closure_forces()
            mujoco.mj_step(m, d)
            if step % 50 == 0 and np.max(np.abs(d.qvel)) < speed_tol and step * m.opt.timestep > 0.05:
                settled = True
                break
        mujoco.mj_forward(m, d)
        idx = twin.index
        gaps = np.stack([d.site_xpos[a] - d.site_xpos[b] for a, b in zip(idx.site_s1, idx.site_s2)])
        state = TwinState(
            r=d.xpos[idx.platform][None] / MM, R=d.xmat[idx.platform].reshape(1, 3, 3).copy(),
            targets=d.site_xpos[idx.site_targets][None] / MM,
            joint=d.qpos[idx.qadr_base[:2]][None].copy(), gaps=gaps[None] / MM,
            ss_axial=np.array([d.qpos[idx.qadr_slide] / MM]), converged=np.array([settled]),
            iterations=np.array([step]), qpos=d.qpos[None].copy())
        return state, SettleInfo(time=step * m.opt.timestep, settled=settled,
                                 max_speed=float(np.max(np.abs(d.qvel))))
