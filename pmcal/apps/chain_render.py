"""``pmcal --machine DIR twin render``: a PNG of a machine folder's twin at a task pose (routed from
:mod:`pmcal.apps.chain`).

The pose is reached as the twin reaches it (inverse kinematics on the task coordinates of machine.toml,
the chain assembled by :class:`pmcal.twin.closed_chain.ClosedChainTwin` with the errors of ``--errors``);
the picture draws the folder's ``scene.xml`` (else its model) in that configuration, from MuJoCo's free
camera (the scene's ``<statistic>`` and ``<global azimuth/elevation>``). The links are drawn with their
nominal geometry: errors of a fraction of a millimetre do not show at this scale.
"""

from __future__ import annotations

import re

import numpy as np

from pmcal.apps.chain_commands import error_set
from pmcal.errors import InputError, RunError
from pmcal.fileio import atomic_write
from pmcal.option_ranges import parse_task_pose


def twin_render(args) -> int:
    """Write the PNG of ``args.output``: the twin at ``--pose`` (default: the ``home`` keyframe)."""
    from pmcal.twin.render import RenderUnavailable, render_machine_png

    machine = args.selected_machine
    twin = machine.twin
    spec = machine.spec
    pose = parse_task_pose(args.pose, spec.task.coordinates)
    errors = error_set(machine, args.errors)
    params = errors if isinstance(errors, dict) else None
    if pose is None:
        qpos = twin.solve(twin.home_commands[None], params)[0]
    else:
        cmd, reasons = twin.inverse_report(pose[None], params)
        if reasons[0]:
            raise InputError(f"pose {args.pose}: {reasons[0]}", field="--pose")
        qpos = twin.solve(cmd, params)[0]
    if not np.isfinite(qpos).all():
        raise InputError(f"the chain of {machine.name} does not assemble at pose {args.pose or 'home'}",
                         field="--pose")
    try:
        png = render_machine_png(machine.spec, qpos, args.width, args.height)
    except RenderUnavailable as exc:
        raise RunError(str(exc)) from None
    except ValueError as exc:                  # the scene adds joints, or includes a file that is not there
        raise InputError(_scene_problem(str(exc), machine.spec.model_path.name),
                         file=str(machine.spec.folder / "scene.xml")) from None
    with atomic_write(args.output, "wb") as fh:
        fh.write(png)
    return 0


def _scene_problem(message: str, model_name: str) -> str:
    """One line for MuJoCo's (multi-line) complaint about a folder's ``scene.xml``; an include of a file that
    is not there (a copied machine whose model was renamed) names the fix."""
    missing = re.search(r"Error opening file '([^']*)'", message)
    if missing:
        return (f"includes {missing.group(1)}, which is not in the machine folder: include the model, "
                f'<include file="{model_name}"/>')
    return " ".join(message.split())
