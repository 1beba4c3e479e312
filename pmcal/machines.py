"""Registry of machines: a built-in name (a folder under ``mjcf/``) or any folder holding ``<name>.xml``
and ``machine.toml``, routed to the application module that implements its commands.

An application module implements the subcommands that make sense for its machine as functions taking
the parsed ``argparse`` namespace and returning an exit status (``identify``, ``compensate``,
``twin_measure``, ...), and ``option_help(machine)``: the table of per-machine help texts of
:mod:`pmcal.commands.options`. A command a machine does not implement is refused with a clear message.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

from pmcal.errors import InputError
from pmcal.mjcf import ROOT as MJCF_ROOT

#: the machine of ``pmcal`` without ``--machine``
DEFAULT_MACHINE = "ocpm_2dof"
#: the seeded machines with application modules of their own (their TOML files say ``legacy``)
LEGACY_APPS: dict[str, str] = {
    "ocpm_2dof": "pmcal.apps.ocpm",
    "planar_2dof": "pmcal.apps.planar",
}
#: application of every other machine folder
GENERIC_APP = "pmcal.apps.chain"
#: the configuration file of a machine folder
TOML_NAME = "machine.toml"


def builtin_names() -> list[str]:
    """Names of the built-in machines: folders under ``mjcf/`` holding a ``machine.toml``."""
    return sorted(p.parent.name for p in MJCF_ROOT.glob(f"*/{TOML_NAME}"))


def machine_dir(name: str) -> Path:
    """Folder of a built-in machine's model and configuration (``mjcf/<name>/``)."""
    return MJCF_ROOT / name


def machine_folder(value: str | Path) -> Path:
    """The folder ``value`` names: a built-in name, else a path to a folder with a ``machine.toml``.

    Raises :class:`~pmcal.errors.InputError` (field ``--machine``) for anything else.
    """
    text = str(value)
    if text in builtin_names():
        return machine_dir(text)
    path = Path(text).expanduser()
    if path.is_dir():
        if not (path / TOML_NAME).is_file():
            raise InputError(f"machine folder {path} holds no {TOML_NAME} (docs/ADDING_A_MACHINE.md)",
                             field="--machine")
        return path
    if path.exists():
        raise InputError(f"{path} is a file; --machine takes a built-in name or a machine folder",
                         field="--machine")
    raise InputError(f"unknown machine '{text}': neither a built-in name ({', '.join(builtin_names())}) nor a "
                     "folder holding NAME.xml and machine.toml", field="--machine")


@dataclass(frozen=True)
class MachineEntry:
    """A machine as the command line sees it: ``name``, ``folder`` and the application module's name."""

    name: str
    folder: Path
    app_name: str

    @property
    def app(self) -> ModuleType:
        return importlib.import_module(self.app_name)

    def option_help(self) -> dict:
        """The application's per-machine help table (:mod:`pmcal.commands.options`)."""
        return self.app.option_help(self)


def resolve(value: str | Path) -> MachineEntry:
    """The machine ``--machine VALUE`` selects."""
    folder = machine_folder(value)
    name = folder.name if str(value) not in LEGACY_APPS else str(value)
    return MachineEntry(name, folder, LEGACY_APPS.get(name, GENERIC_APP))


def get_app(name: str) -> ModuleType:
    return resolve(name).app


def dispatch(command: str, args) -> int:
    """Run ``command`` of the machine selected by ``args.machine``."""
    entry = getattr(args, "machine_entry", None) or resolve(args.machine)
    func = getattr(entry.app, command, None)
    if func is None:
        raise InputError(f"'{command.replace('_', ' ')}' is not available for machine '{entry.name}'",
                         field="--machine")
    return int(func(args) or 0)
