"""The whole job on a machine described by a folder, as library functions: a virtual measurement campaign on
its twin, identification to a parameters document, targets spread over its workspace, compensation of a
target list. The command line (:mod:`pmcal.apps.chain`) is a thin layer over these.

Units: commands deg (revolute) / mm (prismatic), targets and task positions mm (base frame), angles deg.
Errors are ``{key: value}`` in each key's unit (``machine.twin.error_units``); an absent key is nominal.

Example
-------
>>> from pmcal.machines import Machine
>>> m = Machine.builtin("delta_3dof")                                  # doctest: +SKIP
>>> meas, truth = campaign(m, 48, seed=3)                               # doctest: +SKIP
>>> res = identify(m, meas)                                             # doctest: +SKIP
>>> task = sample_targets(m, 12, seed=1)                                # doctest: +SKIP
>>> commands = compensate(m, res.params, task)                          # doctest: +SKIP
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from pmcal import progress
from pmcal.errors import InputError, RunError
from pmcal.io_chain import ChainMeasurements

#: poses measured per step of the progress bar
_CHUNK = 8


def random_errors(machine, rng: np.random.Generator) -> dict[str, float]:
    """One geometric error set of the machine's size: each error of ``machine.twin.error_keys`` drawn
    normal with the prior size ``machine.toml [errors]`` gives it (mm / deg)."""
    twin = machine.twin
    return {k: float(v) for k, v in zip(twin.error_keys, rng.normal(0.0, twin.prior_std()))}


def campaign(machine, poses: int, *, seed: int = 1, errors: str | Mapping[str, float] = "random",
             sigma_mm: float | None = None, task: np.ndarray | None = None,
             seconds_per_pose: float = 30.0, source: str | None = None) -> tuple[ChainMeasurements, dict[str, float]]:
    """A virtual measurement campaign on the machine's twin.

    Parameters
    ----------
    machine : :class:`pmcal.machines.Machine` (not a seeded one).
    poses : number of poses; their commands are drawn over the workspace box of machine.toml (the nominal
        machine's inverse kinematics, as a controller would), unless ``task`` is given.
    seed : seed of the errors, the commands and the tracker noise, drawn in this order.
    errors : ``"random"`` (:func:`random_errors`), ``"none"``, or an error set ``{key: value}``.
    sigma_mm : tracker noise, 1 sigma per coordinate, mm (default machine.toml's).
    task : (n, C) explicit targets in the machine's task coordinates instead of drawn poses.
    seconds_per_pose : time between poses, s (the ``time_s`` column).
    source : the file ``task`` came from (for messages).

    Returns
    -------
    (measurements, truth) : the measured targets (mm, base frame; poses the erroneous machine cannot
    assemble are replaced by further draws) and the error set measured.
    """
    twin = machine.twin
    rng = np.random.default_rng(seed)
    if isinstance(errors, str):
        truth = random_errors(machine, rng) if errors == "random" else {}
    else:
        truth = dict(errors)
    sigma = twin.sigma_mm if sigma_mm is None else float(sigma_mm)
    if task is not None:
        commands = twin.inverse(task, None)
        bad = np.flatnonzero(~np.isfinite(commands).all(axis=1))
        if bad.size:
            raise InputError("target out of reach of the nominal machine", file=source, row=int(bad[0]) + 1,
                             field=machine.spec.task.coordinates[0])
    else:
        commands = twin.sample_commands(poses, rng)
    got_cmd, got_y = [], []
    with progress.progress(total=len(commands), desc="measuring", unit="pose") as bar:
        for start in range(0, len(commands), _CHUNK):
            cmd = commands[start:start + _CHUNK]
            y = twin.measure(cmd, truth, rng, sigma)
            ok = np.isfinite(y).all(axis=(1, 2))
            got_cmd.append(cmd[ok])
            got_y.append(y[ok])
            bar.update(len(cmd))
    commands, y = np.concatenate(got_cmd), np.concatenate(got_y)
    short = (poses if task is None else len(task)) - len(commands)
    if short and task is not None:
        raise RunError(f"{short} of the targets cannot be assembled on the erroneous machine")
    for _ in range(20):
        if short <= 0:
            break
        cmd = twin.sample_commands(short, rng)
        more = twin.measure(cmd, truth, rng, sigma)
        ok = np.isfinite(more).all(axis=(1, 2))
        commands, y = np.concatenate([commands, cmd[ok]]), np.concatenate([y, more[ok]])
        short -= int(ok.sum())
    if short > 0:
        raise RunError(f"the erroneous machine assembles too few of the drawn poses ({short} missing)")
    n = len(commands)
    meas = ChainMeasurements(pose_id=[f"P{i + 1}" for i in range(n)], commands=commands, targets=y,
                             time_s=np.arange(n) * float(seconds_per_pose))
    return meas, truth


def check_assembles(machine, meas: ChainMeasurements, limit_mm: float = 50.0) -> None:
    """Catch a wrong unit or a mislabelled row before identifying: every measured target within
    ``limit_mm`` of where the nominal machine puts it at the row's commands, and every row's commands
    assemble the nominal chain. An :class:`InputError` names file, row and field."""
    y0 = machine.twin.targets(meas.commands)
    motors = machine.spec.motor_columns
    for i in np.flatnonzero(~np.isfinite(y0).all(axis=(1, 2))):
        raise InputError("the nominal machine cannot assemble at these commands (wrong machine or units?)",
                         file=meas.path, row=int(i) + 1, field=motors[0])
    d = np.linalg.norm(meas.targets - y0, axis=2)
    bad = np.argwhere(d > limit_mm)
    if bad.size:
        i, k = (int(v) for v in bad[0])
        scale = np.linalg.norm(meas.targets[i, k]) / max(np.linalg.norm(y0[i, k]), 1e-9)
        hint = " (values look like metres: the file must be in mm)" if 5e-4 < scale < 2e-3 else ""
        raise InputError(f"target t{k + 1} is {d[i, k]:.4g} mm from where the nominal machine puts it (limit "
                         f"{limit_mm:g} mm){hint}", file=meas.path, row=i + 1, field=f"t{k + 1}_x")


def sample_targets(machine, count: int, seed: int = 1) -> np.ndarray:
    """``count`` targets (count, C) in the machine's task coordinates, drawn uniformly over the workspace
    box of machine.toml and kept where the nominal machine reaches them within its motor ranges."""
    twin = machine.twin
    rng = np.random.default_rng(seed)
    commands = twin.sample_commands(count, rng)
    return twin.forward(commands)


def compensate(machine, params: Mapping[str, float], task: np.ndarray, path: str | None = None) -> np.ndarray:
    """Motor commands (n, M) that put the task site of the machine with errors ``params`` at ``task`` (n, C):
    its inverse kinematics with the identified errors. A target it cannot reach is an :class:`InputError`
    naming the row of ``path`` and the reason."""
    commands, reasons = machine.twin.inverse_report(task, dict(params))
    for i, why in enumerate(reasons):
        if why:
            raise InputError(f"not reachable by the identified machine: {why}", file=path, row=i + 1,
                             field=machine.spec.task.coordinates[0])
    return commands
