"""Build the planar robot's MuJoCo model with the machine's geometry and errors inserted (``MjSpec`` edits).

The nominal MJCF (``mjcf/planar_2dof/planar_2dof.xml``) is the template; positions are rewritten from
machine.toml plus the errors, so the parallelograms stay parallelograms (a geometric error moves both
bars of a pair) and the platform stays translational, as in the paper's model. Zero offsets turn the
active links' body frames about their joint axes: the motor joint reads the commanded angle while the
link sits ``Δθ`` further on. The MAEMM ``ΔrM`` moves the mechanism's base joint O1.

Frames and units: this module and :mod:`pmcal.twin.planar.twin` are the only places that convert between the
seed plane (mm; x, y up) and MuJoCo's world (m; x, z up; y out of the plane).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from pmcal.mechanism.planar.geometry import Errors
from pmcal.mechanism.planar.kinematics import forward, mm_vector
from pmcal.twin.planar.config import MODEL_XML, PlanarMachine

MM = 1e-3  # metres per millimetre

MOTOR_JOINTS = ("right_motor", "left_motor")
CLOSURES = ("closure_right_proximal", "closure_right_distal", "closure_left", "closure_scale")


def local(v_mm) -> list[float]:
    """A seed-plane vector (mm) as a MuJoCo vector (m) in a frame whose x, z span the plane."""
    v = np.asarray(v_mm, dtype=float)
    return [v[0] * MM, 0.0, v[1] * MM]


def hinge_quat(angle: float) -> list[float]:
    """Quaternion of a turn by ``angle`` (rad) about the joints' axis, world -y (seed counter-clockwise)."""
    return [float(np.cos(angle / 2)), 0.0, float(-np.sin(angle / 2)), 0.0]


def scale_reference(machine: PlanarMachine) -> float:
    """|O1 O2| (mm) of the nominal machine at home: the slide joint reads the length minus this."""
    g = machine.geometry
    return float(np.linalg.norm(mm_vector(g, forward(g, g.home))))


def build_spec(machine: PlanarMachine, errors: Errors | None = None, path=MODEL_XML) -> mujoco.MjSpec:
    """The MJCF template with ``machine``'s geometry and ``errors`` written in (not compiled)."""
    err = errors if errors is not None else Errors()
    g = machine.geometry.perturbed(err)
    a, s = machine.twin.parallelogram_proximal, machine.twin.parallelogram_distal
    spec = mujoco.MjSpec.from_file(str(path))
    body, site = spec.body, spec.site
    body("base").pos = [0.0, 0.0, machine.twin.base_height_m]
    site("A1").pos, site("A2").pos = local(g.e[0]), local(g.e[1])
    site("O1").pos = local(g.c)
    # limb 1: active + passive proximal links (parallelogram), shaft, two distal bars (parallelogram)
    body("right_proximal").pos = local(g.e[0])
    body("right_proximal").quat = hinge_quat(err.dtheta[0])
    body("right_passive").pos = local(g.e[0] + a)
    site("right_passive_tip").pos = local([g.L[0], 0.0])
    body("right_shaft").pos = local([g.L[0], 0.0])
    site("right_shaft_top").pos = local(a)
    body("platform").pos = local([g.l[0], 0.0])
    body("right_distal_b").pos = local(s)
    site("right_distal_b_tip").pos = local([g.l[0], 0.0])
    site("platform_right_b").pos = local(s)
    site("O2").pos = local(-g.d)
    # limb 2
    body("left_proximal").pos = local(g.e[1])
    body("left_proximal").quat = hinge_quat(err.dtheta[1])
    body("left_distal").pos = local([g.L[1], 0.0])
    site("left_distal_tip").pos = local([g.l[1], 0.0])
    # measuring mechanism: base joint O1 = c + ΔrM, slider rod end at the reference length
    body("scale_plate").pos = local(g.c)
    site("scale_tip").pos = local([scale_reference(machine), 0.0])
    return spec


@dataclass(frozen=True)
class PlanarIndex:
    """Ids and addresses the twin needs. ``site_s1``, ``site_s2``, ``qadr_base``, ``dadr_base``, ``qadr_slide``
    and ``dadr_slide`` are the fields :class:`pmcal.twin.assembly.BatchAssembler` reads (closure site pairs, the
    motors it holds, and a slide it may load: here the scale's, with zero stiffness)."""

    site_s1: np.ndarray          # first site of each closure (CLOSURES order)
    site_s2: np.ndarray          # second site
    site_P: int
    site_O2: int
    qadr_base: np.ndarray        # qpos addresses of the motors right_motor, left_motor
    dadr_base: np.ndarray        # dof addresses of the motors (held during assembly)
    qadr: dict                   # joint name -> qpos address
    qadr_slide: int
    dadr_slide: int

    @classmethod
    def of(cls, m: mujoco.MjModel) -> "PlanarIndex":
        obj = mujoco.mjtObj
        eq = [mujoco.mj_name2id(m, obj.mjOBJ_EQUALITY, n) for n in CLOSURES]
        if min(eq) < 0:
            raise ValueError("model lacks the closure constraints " + ", ".join(CLOSURES))
        if np.any(m.eq_objtype[eq] != obj.mjOBJ_SITE):
            raise ValueError("closures must be site-based connects")
        jid = {m.joint(j).name: j for j in range(m.njnt)}
        motors = [jid[n] for n in MOTOR_JOINTS]
        slide = jid["scale_slide"]
        return cls(site_s1=m.eq_obj1id[eq].copy(), site_s2=m.eq_obj2id[eq].copy(),
                   site_P=mujoco.mj_name2id(m, obj.mjOBJ_SITE, "P"),
                   site_O2=mujoco.mj_name2id(m, obj.mjOBJ_SITE, "O2"),
                   qadr_base=m.jnt_qposadr[motors].copy(), dadr_base=m.jnt_dofadr[motors].copy(),
                   qadr={n: int(m.jnt_qposadr[j]) for n, j in jid.items()},
                   qadr_slide=int(m.jnt_qposadr[slide]), dadr_slide=int(m.jnt_dofadr[slide]))


def build_model(machine: PlanarMachine, errors: Errors | None = None, path=MODEL_XML) -> tuple[mujoco.MjModel, PlanarIndex]:
    """Compiled model of the real machine and its index."""
    m = build_spec(machine, errors, path).compile()
    return m, PlanarIndex.of(m)
