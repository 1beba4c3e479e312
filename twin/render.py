"""Offscreen pictures of a machine (PNG bytes), for reports and model READMEs: a machine folder's
(:func:`render_machine_png`) or any compiled model (:func:`render_model_png`).

Uses ``mujoco.Renderer`` headless: set ``MUJOCO_GL=egl`` (default here) or ``osmesa`` before MuJoCo
creates its first context.
"""

from __future__ import annotations

import io
import os

import numpy as np

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402


class RenderUnavailable(RuntimeError):
    """No offscreen OpenGL context could be created."""


def render_machine_png(spec, qpos: np.ndarray, width: int = 800, height: int = 600) -> bytes:
    """PNG of a machine folder (``spec``: its :class:`pmcal.mechanism.machine_spec.MachineSpec`): its
    ``scene.xml`` (else its model) at configuration ``qpos`` (of the model's joints), from MuJoCo's free
    camera (the scene's ``<statistic>`` and ``<global azimuth/elevation>``). ValueError when the scene adds
    joints to the model."""
    scene = spec.folder / "scene.xml"
    m = mujoco.MjModel.from_xml_path(str(scene if scene.is_file() else spec.model_path))
    if m.nq != len(qpos):
        raise ValueError(f"{m.nq} joint coordinates, the model {len(qpos)}: the scene must include the model and "
                         "add no joints")
    # the offscreen buffer must hold the image (MJCF <visual><global offwidth/offheight>, default 640 x 480)
    m.vis.global_.offwidth = max(int(m.vis.global_.offwidth), width)
    m.vis.global_.offheight = max(int(m.vis.global_.offheight), height)
    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    mujoco.mj_forward(m, d)
    cam = mujoco.MjvCamera()
    mujoco.mjv_defaultFreeCamera(m, cam)
    option = None
    if not visible_moving_geoms(m):            # nothing of the machine would show: draw its skeleton and sites
        option = mujoco.MjvOption()
        option.flags[mujoco.mjtVisFlag.mjVIS_AUTOCONNECT] = True
        option.sitegroup[:] = 1
    return render_model_png(m, d, width, height, cam, option)


def visible_moving_geoms(m: mujoco.MjModel) -> int:
    """How many geoms of the bodies (not the world's: a scene's floor) a picture shows: MuJoCo's visible groups
    (0-2) and not transparent. A CAD export whose meshes were left out (Git LFS files absent) has none; its
    picture is then the kinematic skeleton (MuJoCo's ``mjVIS_AUTOCONNECT``) with every site."""
    shown = (m.geom_bodyid > 0) & (m.geom_group < 3) & (m.geom_rgba[:, 3] > 0)
    return int(np.sum(shown))


def render_model_png(m: mujoco.MjModel, d: mujoco.MjData, width: int, height: int, camera=None,
                     option: mujoco.MjvOption | None = None) -> bytes:
    """PNG of any model in state ``d`` (forward already run), seen from ``camera`` (name, id or MjvCamera), with
    the visualisation ``option`` (default MuJoCo's)."""
    try:
        renderer = mujoco.Renderer(m, height=height, width=width)
    except Exception as exc:  # MuJoCo raises FatalError without a usable OpenGL context
        raise RenderUnavailable(f"offscreen rendering is unavailable (MUJOCO_GL={os.environ.get('MUJOCO_GL')}): "
                                f"{exc}; install EGL (libegl1) or OSMesa and set MUJOCO_GL=egl|osmesa") from None
    try:
        renderer.update_scene(d, camera=camera if camera is not None else -1, scene_option=option)
        return _to_png(renderer.render())
    finally:
        renderer.close()


def _to_png(pixels: np.ndarray) -> bytes:
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.image

    buf = io.BytesIO()
    matplotlib.image.imsave(buf, pixels, format="png")
    return buf.getvalue()
