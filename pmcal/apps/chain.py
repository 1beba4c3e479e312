"""Application of a machine described by a folder (``--machine DIR``, or a built-in name of a
``kind = "chain"`` folder): its command-line wording and defaults from its machine.toml, and the routing of
its commands (:data:`ROUTES`: ``twin measure``, ``identify``, ``targets``, ``compensate``, ``evaluate`` to
:mod:`pmcal.apps.chain_commands`; ``twin render``, ``twin plan``, ``demo``, ``diagnose``, ``loop`` to their
own modules), imported on first use like :mod:`pmcal.apps.ocpm`'s: building the parser (``--help``) needs only
this module, a command imports the twin and SciPy.
"""

from __future__ import annotations

import importlib

from pmcal.io_chain import setpoint_columns

#: choices of ``twin measure --errors`` besides a parameters file
ERROR_CHOICES = ("random", "none")
#: defaults of the commands
DEFAULT_POSES = 48


def command_defaults(machine) -> dict:
    """Defaults of the commands for ``machine`` (:func:`pmcal.commands.routing.command_defaults`): campaign poses,
    tracker noise (mm, from machine.toml), the twin's error set."""
    return {"poses": DEFAULT_POSES, "sigma_mm": machine.spec.sigma_mm, "errors": "random"}


def option_help(machine) -> dict:
    """The command line's wording for ``machine`` (:mod:`pmcal.commands.options`): its columns, units and
    defaults from its machine.toml (the seeded machines' options it does not have say so where they are
    added: their ``kinds``)."""
    spec = machine.spec
    task = ", ".join(spec.task.coordinates)
    motors = ", ".join(setpoint_columns(spec))
    table = {}
    sigma = f"{spec.sigma_mm:g} mm from machine.toml [tracker] sigma_mm"
    table.update({
        ("twin measure", "--errors"): {
            "metavar": "random|none|PARAMS.json",
            "help": "error set of the virtual machine: random (default; each error drawn with the size "
                    "machine.toml [errors] gives, from --seed), none, or a parameters file (docs/formats.md)"},
        ("twin measure", "--poses"): f"number of poses, commands drawn over the workspace (default "
                                     f"{DEFAULT_POSES})",
        ("twin measure", "--targets"): f"explicit targets ({task}) instead of drawn poses",
        ("twin measure", "--noise"): f"tracker noise, standard deviation per coordinate, mm (default {sigma})",
        ("twin measure", "--seed"): "random seed (errors, poses, noise)",
        ("twin measure", "--seconds-per-pose"): "time between poses, s (time_s column; default 30)",
        ("identify", "--sigma"): f"tracker noise, mm (default {sigma})",
        ("identify", "-o"): "parameters file to write (values, uncertainty, identifiable set: docs/formats.md)",
        ("identify", "--history"): {"metavar": "DIR", "help": "also file the result into this machine history "
                                    "folder (one JSON per calibration, never overwritten; 'pmcal history DIR' "
                                    "says what moved since the previous one; docs/formats.md)"},
        ("targets", ""): f"write a targets CSV: {task} spread over the workspace of machine.toml",
        ("targets", "--seed"): "random seed of the sample (default 1)",
        ("compensate", ""): f"corrected motor commands for targets ({task})",
        ("compensate", "--targets"): f"targets CSV: {task} ('pmcal --machine {spec.name} targets' writes one)",
        ("compensate", "-o"): f"setpoints CSV to write: the targets with {motors} appended",
        ("compensate", "--table"): "write the compensation table for the PLC (format 4: JSON, CSV beside) over "
                                   f"the [table] axes ({', '.join(spec.table_axes) or 'none: offline only'})",
        ("compensate", "--grid"): {"metavar": "N1,N2,..", "help": "table nodes per [table] axis (default: "
                                   "machine.toml [table] nodes)"},
        ("compensate", "--table-version"): "table version (1..2**32-1, must increase on the PLC); default: Unix time",
        ("compensate", "--absolute"): "the table holds absolute motor commands (nReference 0) instead of the "
                                      "corrections to add to the controller's own nominal IK (nReference 2, "
                                      f"default unless [table] reference = \"none\"); docs/compensation_table.md",
        ("evaluate", ""): "position error of a parameter set against a measurement file (RMS, mm)",
    })
    table.update({
        ("loop", ""): "twin in the loop: the task site's position error at held-out targets before and after "
                      "the identified compensation table is pushed to a mock PLC (docs/bridge.md)",
        ("loop", "--errors"): {
            "metavar": "random|none|PARAMS.json",
            "help": "error set of the virtual machine: random (default; each error drawn with the size "
                    "machine.toml [errors] gives, from --seed, as 'demo --seed' draws them), none, or a "
                    "parameters file"},
        ("loop", "--targets"): "number of held-out targets, uniform inside the table's grid (default 24)",
        ("loop", "--grid"): {"metavar": "N1,N2,..", "default": None,
                             "help": "table nodes per [table] axis (default: machine.toml [table] nodes)"},
        ("loop", "--seed"): "random seed of the errors, the planned campaign and its noise (as 'demo --seed'), "
                            "and of the held-out targets and the tracker's noise on them (default 1)",
        ("loop", "--json"): "write the summary as JSON (rms/max before/after/direct, push, grid, timings)",
    })
    table.update({
        ("twin render", "--pose"): {
            "metavar": ",".join(spec.task.coordinates), "default": None,
            "help": f"task pose ({task}; mm, deg) the twin reaches by inverse kinematics (default: "
                    + (f"the '{spec.home}' keyframe)" if spec.home else "the model's default configuration)")},
        ("twin render", "--errors"): "error set of the real machine: a parameters file (default none)",
        ("diagnose", ""): "what the geometric model leaves in a campaign: backlash, zero drift, frame drift, "
                          "thermal expansion named only when they hold on held-out rows, else unexplained",
        ("diagnose", "--sigma"): f"tracker noise, mm (default {sigma})",
        ("demo", ""): f"the whole job on {spec.name}'s twin: planned campaign, identification, compensation, "
                      "HTML report",
        ("demo", "--seed"): "random seed of the virtual machine's errors and the campaign (default 1)",
        ("twin plan", ""): "write the poses to measure, chosen D-optimally for identification (plan CSV)",
        ("twin plan", "--poses"): {"default": DEFAULT_POSES,
                                   "help": f"number of poses (default {DEFAULT_POSES})"},
        ("twin plan", "--seed"): "random seed of the candidate poses (default 1)",
        ("twin plan", "-o"): f"plan CSV to write: pose_id, {', '.join(spec.motor_columns)} in driving order",
        ("twin measure", "--plan"): "the commands of a plan ('twin plan') instead of drawn poses",
    })
    return table


#: command -> module that implements it (a function of the same name taking the parsed arguments)
ROUTES = {**{name: "pmcal.apps.chain_commands"
             for name in ("twin_measure", "identify", "targets", "compensate", "evaluate", "export_model",
                          "import_campaign")},
          "twin_render": "pmcal.apps.chain_render", "twin_plan": "pmcal.apps.chain_plan",
          "demo": "pmcal.apps.chain_demo", "diagnose": "pmcal.apps.chain_diagnose", "loop": "pmcal.apps.chain_loop"}


def __getattr__(name: str):
    if name not in ROUTES:
        raise AttributeError(name)
    return getattr(importlib.import_module(ROUTES[name]), name)
