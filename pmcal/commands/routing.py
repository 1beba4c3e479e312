"""From a machine to the code that runs its commands: the application module its ``machine.toml`` names
(:data:`pmcal.machines.LEGACY_APPS`, :data:`pmcal.machines.GENERIC_APP`), imported here, in the command
layer, above the applications (the library's :class:`~pmcal.machines.Machine` only names it).

An application module implements the subcommands that make sense for its machine as functions taking the
parsed ``argparse`` namespace and returning an exit status (``identify``, ``compensate``,
``twin_measure``, ...), ``option_help(machine)`` (the table of per-machine help texts of
:mod:`pmcal.commands.options`) and ``command_defaults(machine)``. A command a machine does not implement is
refused with a clear message.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from pmcal.errors import InputError
from pmcal.machines import Machine, resolve


def application(machine: Machine) -> ModuleType:
    """The application module of ``machine`` (``machine.app_name``)."""
    return importlib.import_module(machine.app_name)


def option_help(machine: Machine) -> dict:
    """The machine's per-command help table (:mod:`pmcal.commands.options`)."""
    return application(machine).option_help(machine)


def command_defaults(machine: Machine) -> dict:
    """Defaults of the machine's commands (``twin measure --poses``, ``--noise``, ...)."""
    return application(machine).command_defaults(machine)


def dispatch(command: str, args) -> int:
    """Run ``command`` of the machine selected by ``args.machine``."""
    machine = getattr(args, "selected_machine", None) or resolve(args.machine)
    func = getattr(application(machine), command, None)
    if func is None:
        raise InputError(f"'{command.replace('_', ' ')}' is not available for machine '{machine.name}'",
                         field="--machine")
    return int(func(args) or 0)
