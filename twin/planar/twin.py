"""The planar robot's digital twin: the generic closed-chain core on ``mjcf/planar_2dof/chain``.

The machine is data (docs/closed_chain.md, "Seeded machines"): the MJCF, its linear scale as a ``"distance"``
measurement between O1 and O2, the task point P in the seed frame O-xy (site O), and the paper's error
names mapped onto frame displacements (``[names]``). :class:`PlanarTwin` closes the loops with
:class:`pmcal.twin.closed_chain.ClosedChainTwin` (Newton with the motors held, on the home branch) and reads
P and |O1 O2|; :func:`measure` runs the paper's campaigns (servo error eq. 35 on the held angles, one scale
error eq. 34 per reading). Interface units: mm and radians (seed plane); SI inside MuJoCo.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import mujoco
import numpy as np

from pmcal.errors import RunError
from pmcal.mechanism.machine_spec import MachineSpec, expand_names
from pmcal.mechanism.planar.geometry import Errors
from pmcal.mechanism.planar.kinematics import forward, inverse
from pmcal.mechanism.planar.noise import Noise
from pmcal.mjcf import machine_dir
from pmcal.twin.closed_chain import ClosedChainTwin
from pmcal.twin.planar.config import SCENE_XML, PlanarMachine, default_machine

#: the planar robot described as data for the generic core
CHAIN_DIR = machine_dir("planar_2dof") / "chain"


@lru_cache(maxsize=1)
def chain_twin() -> ClosedChainTwin:
    """The generic twin of ``mjcf/planar_2dof/chain`` (cached: its warm starts serve every later solve)."""
    return ClosedChainTwin(MachineSpec.load(CHAIN_DIR))


@dataclass
class PlanarPoses:
    """Assembled poses (N of them): r (N, 2) position of P, mm (seed frame); length (N,) |O1 O2|, mm;
    motor (N, 2) held motor angles, rad; qpos (N, nq) MuJoCo configurations."""

    r: np.ndarray
    length: np.ndarray
    motor: np.ndarray
    qpos: np.ndarray


class PlanarTwin:
    """A real planar robot: the nominal MJCF with ``errors`` (zero offsets, geometric errors, MAEMM)."""

    #: cells (mm) of the positions this twin has solved by task-space continuation (:meth:`assemble`)
    CELL_MM = 5.0

    def __init__(self, errors: Errors | None = None, machine: PlanarMachine | None = None):
        self.machine = machine or default_machine()
        self.errors = errors if errors is not None else Errors()
        self.chain = chain_twin()
        self._known_cells: set = set()
        self.params = expand_names(self.chain.spec.names, self.errors.as_interface())

    @property
    def model(self) -> mujoco.MjModel:
        """The compiled model with this machine's frame errors written in (zero offsets are joint offsets)."""
        self.chain.set_params(self.params)
        return self.chain.model

    def assemble(self, motor: np.ndarray) -> PlanarPoses:
        """Close the loops with the motor joints at ``motor`` (N, 2) rad (what the servos really hold: the
        zero offsets are added here) and read P and |O1 O2|. RunError where the chain does not assemble."""
        motor = np.atleast_2d(np.asarray(motor, dtype=float))
        self._learn_branch(motor)
        q = self.chain.solve(np.rad2deg(motor), self.params)
        bad = ~np.isfinite(q).all(axis=1)
        if bad.any():
            raise RunError(f"the twin did not assemble at motor angles {np.rad2deg(motor[bad][0])} deg")
        return PlanarPoses(r=self.chain.task_of(q), length=self.chain.observe_at(q)[:, 0], motor=motor, qpos=q)


    def _learn_branch(self, motor: np.ndarray) -> None:
        """Solve new regions of the workspace by task-space continuation from home first (inverse
        kinematics at the positions the closed forms give, one per 5 mm cell): the straight motor path from
        home to a far pose may cross a singularity onto another assembly branch; the poses solved here are
        the warm starts, on the paper's branch, of every later solve near them."""
        r = forward(self.machine.geometry, motor)
        cells = np.round(r / self.CELL_MM)
        known = self._known_cells
        new = {}
        for cell, pos in zip(map(tuple, cells), r):
            if cell not in known and cell not in new and np.isfinite(pos).all():
                new[cell] = pos
        if new:
            self.chain.inverse(np.array(list(new.values())), self.params)
            known.update(new)


@dataclass
class Campaign:
    """Chains of readings (rad, mm): theta_cmd (S, K, 2) commanded angles; readings (S, K-1) scale changes
    between adjacent positions; poses the S*K assembled poses (row-major)."""

    theta_cmd: np.ndarray
    readings: np.ndarray
    poses: PlanarPoses


def measure(twin: PlanarTwin, theta_cmd: np.ndarray, noise: Noise, rng: np.random.Generator) -> Campaign:
    """Measure chains of positions: ``theta_cmd`` (K, 2) or (S, K, 2) rad, S independent chains; each pose
    held at the command plus the servo error, each reading the change of |O1 O2| plus one scale error."""
    cmd = np.asarray(theta_cmd, dtype=float)
    cmd3 = cmd[None] if cmd.ndim == 2 else cmd
    S, K, _ = cmd3.shape
    poses = twin.assemble((cmd3 + rng.normal(0.0, noise.servo, cmd3.shape)).reshape(S * K, 2))
    readings = np.diff(poses.length.reshape(S, K), axis=1) + rng.normal(0.0, noise.scale, (S, K - 1))
    return Campaign(theta_cmd=cmd3, readings=readings, poses=poses)


def batch_measure(twin: PlanarTwin, noise: Noise, rng: np.random.Generator):
    """A ``measure(theta_cmd (S, K, 2), ids)`` callback for :func:`pmcal.calib.planar.calibration.calibrate_many`."""
    def run(theta_cmd: np.ndarray, ids: np.ndarray) -> np.ndarray:
        return measure(twin, theta_cmd, noise, rng).readings
    return run


def commands_for(twin: PlanarTwin, r: np.ndarray, comp: np.ndarray | None = None) -> np.ndarray:
    """Motor commands (K, 2) rad that the controller sends for nominal positions ``r`` (K, 2) mm (the paper's
    eq. 3 on the nominal geometry), with zero-offset compensation ``comp`` (rad) if given."""
    theta = inverse(twin.machine.geometry, r)
    if not np.all(np.isfinite(theta)):
        raise ValueError("a position is out of the nominal robot's reach")
    return theta - (np.zeros(2) if comp is None else comp)


def render_png(twin: PlanarTwin, motor: np.ndarray | None = None, width: int = 800, height: int = 600,
               camera: str = "front") -> bytes:
    """PNG of the machine (``scene.xml``: floor, light, ``camera``) with the motors at ``motor`` (2,) rad
    (default: home), the loops closed by the twin; the links drawn with their nominal geometry (errors of a
    fraction of a millimetre do not show)."""
    from pmcal.twin.render import render_model_png

    motor = twin.machine.geometry.home if motor is None else np.asarray(motor, dtype=float)
    m = mujoco.MjModel.from_xml_path(str(SCENE_XML))
    d = mujoco.MjData(m)
    d.qpos[:] = twin.assemble(motor[None]).qpos[0]
    mujoco.mj_forward(m, d)
    return render_model_png(m, d, width, height, camera)
