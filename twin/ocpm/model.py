"""Build a "real" machine: the nominal MJCF model plus geometric errors, by compiled-model edits.

Editing ``body_pos`` / ``body_quat`` / ``site_pos`` / ``jnt_pos`` of the compiled model followed by
``mj_setConst`` gives the same model as an ``MjSpec`` edit and recompile, about 100 times faster
(measured on the reference machine): this is what identification loops and Monte Carlo studies use.

The MuJoCo model is in SI units; :class:`pmcal.mechanism.ocpm.params.ErrorSet` is in mm and radians. This module
and :mod:`pmcal.twin.ocpm.assembly` are the only places that convert.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from pmcal.mechanism.ocpm.config import MACHINE_DIR, Geometry, default_geometry
from pmcal.mechanism.ocpm.kinematics import limb_frames
from pmcal.mechanism.ocpm.params import ErrorSet

MM = 1e-3  # metres per millimetre

MODEL_XML = MACHINE_DIR / "ocpm_2dof.xml"
SCENE_XML = MACHINE_DIR / "scene.xml"


@dataclass(frozen=True)
class ModelIndex:
    """Ids and addresses of the named elements the twin needs (resolved once per model)."""

    link1: np.ndarray           # body ids limbJ_link1, J = 1..4
    link2: np.ndarray           # body ids limbJ_link2
    platform: int
    ss_link: int
    site_s1: np.ndarray         # site ids limbJ_S1
    site_s2: np.ndarray         # site ids limbJ_S2
    site_targets: np.ndarray    # site ids T1.. (as many as the model has)
    site_ce: int
    jnt_base: np.ndarray        # joint ids limbJ_B
    jnt_plat: np.ndarray        # joint ids limbJ_A
    jnt_ball: int
    jnt_slide: int
    qadr_base: np.ndarray       # qpos addresses of limbJ_B
    qadr_plat: np.ndarray
    qadr_slide: int
    dadr_base: np.ndarray       # dof addresses of limbJ_B
    dadr_slide: int
    eq_closure: np.ndarray      # equality ids closure_SJ

    @classmethod
    def of(cls, m: mujoco.MjModel, n_limbs: int = 4, target_names=("T1", "T2", "T3")) -> "ModelIndex":
        obj = mujoco.mjtObj
        name = lambda t, n: mujoco.mj_name2id(m, t, n)  # noqa: E731
        ids = lambda t, fmt: np.array([name(t, fmt.format(j)) for j in range(1, n_limbs + 1)])  # noqa: E731
        jb, ja = ids(obj.mjOBJ_JOINT, "limb{}_B"), ids(obj.mjOBJ_JOINT, "limb{}_A")
        slide = name(obj.mjOBJ_JOINT, "ss_slide")
        idx = cls(
            link1=ids(obj.mjOBJ_BODY, "limb{}_link1"), link2=ids(obj.mjOBJ_BODY, "limb{}_link2"),
            platform=name(obj.mjOBJ_BODY, "platform"), ss_link=name(obj.mjOBJ_BODY, "ss_link"),
            site_s1=ids(obj.mjOBJ_SITE, "limb{}_S1"), site_s2=ids(obj.mjOBJ_SITE, "limb{}_S2"),
            site_targets=np.array([name(obj.mjOBJ_SITE, t) for t in target_names]),
            site_ce=name(obj.mjOBJ_SITE, "C_E"),
            jnt_base=jb, jnt_plat=ja, jnt_ball=name(obj.mjOBJ_JOINT, "platform_ball"), jnt_slide=slide,
            qadr_base=m.jnt_qposadr[jb], qadr_plat=m.jnt_qposadr[ja], qadr_slide=int(m.jnt_qposadr[slide]),
            dadr_base=m.jnt_dofadr[jb], dadr_slide=int(m.jnt_dofadr[slide]),
            eq_closure=ids(obj.mjOBJ_EQUALITY, "closure_S{}"),
        )
        missing = [f for f, v in vars(idx).items() if np.any(np.asarray(v) < 0)]
        if missing:
            raise ValueError(f"model lacks named elements: {', '.join(missing)}")
        return idx


def load_model(path: str | Path = MODEL_XML) -> mujoco.MjModel:
    """Load the nominal model (metres)."""
    return mujoco.MjModel.from_xml_path(str(path))


def _quat(R: np.ndarray) -> np.ndarray:
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R).ravel())
    return q


def apply_errors(m: mujoco.MjModel, errors: ErrorSet, geom: Geometry | None = None,
                 index: ModelIndex | None = None, data: mujoco.MjData | None = None) -> mujoco.MjModel:
    """Write ``errors`` into a nominal compiled model in place (positions, frames, link lengths).

    Motor zero offsets (``dtheta``) are not geometry: the twin applies them when it drives the motors.
    Edits are absolute (any earlier errors are overwritten). Pass ``index`` and a scratch ``data`` in
    loops: allocating an ``MjData`` costs ~1 ms, the edits and ``mj_setConst`` ~0.1 ms.
    Returns ``m`` for chaining.
    """
    geom = geom or default_geometry()
    idx = index or ModelIndex.of(m, geom.n_limbs, geom.target_names)
    B = geom.base_points() + errors.db
    A = geom.platform_points() + errors.da
    Q1 = limb_frames(geom.psi, errors.dalpha, errors.dgamma)
    Q2 = limb_frames(geom.psi, errors.dmu, errors.dnu)
    for j in range(geom.n_limbs):
        m.body_pos[idx.link1[j]] = B[j] * MM
        m.body_quat[idx.link1[j]] = _quat(Q1[j])
        m.site_pos[idx.site_s1[j]] = [(geom.l + errors.dl1[j]) * MM, 0.0, 0.0]
        m.body_pos[idx.link2[j]] = A[j] * MM
        m.body_quat[idx.link2[j]] = _quat(Q2[j])
        m.site_pos[idx.site_s2[j]] = [(geom.l + errors.dl2[j]) * MM, 0.0, 0.0]
    # Platform frame = target frame; the ball joint (true C_E) sits at ss_dc in it, on the SS tip.
    dc = np.asarray(errors.ss_dc, dtype=float)
    m.jnt_pos[idx.jnt_ball] = dc * MM
    m.body_pos[idx.platform] = (np.array([0.0, 0.0, geom.h + float(errors.ss_dh)]) - dc) * MM
    for k, site in enumerate(idx.site_targets):
        m.site_pos[site] = geom.targets[k] * MM
    mujoco.mj_setConst(m, data if data is not None else mujoco.MjData(m))
    return m


def build_model(errors: ErrorSet | None = None, geom: Geometry | None = None,
                path: str | Path = MODEL_XML) -> tuple[mujoco.MjModel, ModelIndex]:
    """Load the nominal model and insert ``errors`` (none: the nominal machine)."""
    geom = geom or default_geometry()
    m = load_model(path)
    idx = ModelIndex.of(m, geom.n_limbs, geom.target_names)
    apply_errors(m, errors if errors is not None else ErrorSet(), geom, idx)
    return m, idx
