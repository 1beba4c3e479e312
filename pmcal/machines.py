"""Registry of the machines the CLI knows, each with an application module in :mod:`pmcal.apps`.

An application module implements the subcommands that make sense for its machine as functions taking
the parsed ``argparse`` namespace and returning an exit status: ``demo``, ``identify``, ``compensate``,
``evaluate``, ``diagnose``, ``twin_measure``, ``twin_render``. A command a machine does not implement is
refused with a clear message.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from types import ModuleType

from pmcal.errors import InputError
from pmcal.mjcf import ROOT as MJCF_ROOT_DIR

#: machine name (folder under ``mjcf/``) -> application module
MACHINES: dict[str, str] = {
    "ocpm_2dof": "pmcal.apps.ocpm",
    "planar_2dof": "pmcal.apps.planar",
}

MJCF_ROOT = MJCF_ROOT_DIR


def machine_dir(name: str) -> Path:
    """Folder of a machine's model and configuration (``mjcf/<name>/``)."""
    return MJCF_ROOT / name


def get_app(name: str) -> ModuleType:
    if name not in MACHINES:
        raise InputError(f"unknown machine '{name}' (known: {', '.join(sorted(MACHINES))})",
                         field="--machine")
    return importlib.import_module(MACHINES[name])


def dispatch(command: str, args) -> int:
    """Run ``command`` of the machine selected by ``args.machine``."""
    app = get_app(args.machine)
    func = getattr(app, command, None)
    if func is None:
        raise InputError(f"'{command.replace('_', ' ')}' is not available for machine '{args.machine}'",
                         field="--machine")
    return int(func(args) or 0)
