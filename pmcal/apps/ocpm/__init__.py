"""Application of the over-constrained 2-DoF PM (``--machine ocpm_2dof``, the default).

Each command lives in the module that owns its subject; this module only routes, lazily, so a command
imports only what it needs (:func:`pmcal.commands.routing.dispatch` looks the command up by name).
"""

from __future__ import annotations

import importlib

#: this machine's wording of the commands' options (:mod:`pmcal.commands.options`)
OPTION_HELP = {
    ("twin measure", "--poses"): "number of poses, 1..2000 (default 24)",
    ("identify", "--model"): "error model: whole closed chain (full, default) or the paper's per-limb real "
                             "IK (paper)",
    ("identify", "--method"): "identification method: --model paper hga (default), ga, pso, sa, lm, "
                              "tikhonov, tsvd; --model full the whole-chain least squares",
    ("twin measure", "--preset"): "built-in error set: nominal (default) or paper-table2",
    ("twin render", "--preset"): "built-in error set: nominal (default) or paper-table2",
    ("demo", "--out"): "output folder (report, tables), replaced as a whole; default pmcal-demo, "
                       "pmcal-demo-hidden with --hidden-effect. A folder holding files pmcal did not write is refused",
}

#: command -> module that implements it (a function of the same name taking the parsed arguments)
ROUTES = {
    "twin_measure": "pmcal.apps.ocpm.twin",
    "twin_render": "pmcal.apps.ocpm.twin",
    "twin_plan": "pmcal.apps.ocpm.diagnosis_plan",
    "identify": "pmcal.apps.ocpm.calib",
    "compensate": "pmcal.apps.ocpm.calib",
    "evaluate": "pmcal.apps.ocpm.calib",
    "demo": "pmcal.apps.ocpm.calib",
    "targets": "pmcal.apps.ocpm.twin",
    "diagnose": "pmcal.apps.ocpm.diagnosis",
    "export_model": "pmcal.apps.ocpm.calib",
    "import_campaign": "pmcal.apps.ocpm.calib",
    "loop": "pmcal.apps.ocpm.plc_loop",
}


#: defaults of this machine's commands (:func:`pmcal.commands.routing.command_defaults`)
DEFAULTS = {"poses": 24}


def command_defaults(machine) -> dict:
    """Defaults of the commands (the same for every folder of this machine)."""
    return dict(DEFAULTS)


def option_help(machine) -> dict:
    """The help table of the command line (the same for every folder of this machine)."""
    return OPTION_HELP


def __getattr__(name: str):
    if name not in ROUTES:
        raise AttributeError(name)
    return getattr(importlib.import_module(ROUTES[name]), name)
