"""Offscreen pictures (PNG bytes) of the planar twin, for the report and the model README.

Headless: ``MUJOCO_GL=egl`` (the default set by :mod:`twin`) or ``osmesa``.
"""

from __future__ import annotations

import os

import numpy as np

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402

from pmcal.twin.planar.config import SCENE_XML  # noqa: E402
from pmcal.twin.planar.model import build_spec  # noqa: E402
from pmcal.twin.planar.twin import PlanarTwin  # noqa: E402
from pmcal.twin.render import render_model_png  # noqa: E402


def render_png(twin: PlanarTwin, motor: np.ndarray | None = None, width: int = 800, height: int = 600,
               camera: str = "front") -> bytes:
    """PNG of the twin's machine (``scene.xml``: floor, light, ``camera``) with the motors at ``motor`` (2,)
    rad (default: home), the loops closed by the twin."""
    geom = twin.machine.geometry
    motor = geom.home if motor is None else np.asarray(motor, dtype=float)
    m = build_spec(twin.machine, twin.errors, SCENE_XML).compile()
    d = mujoco.MjData(m)
    d.qpos[:] = twin.assemble(motor[None]).qpos[0]
    mujoco.mj_forward(m, d)
    return render_model_png(m, d, width, height, camera)
