"""Registry of machines: a built-in name (a folder under ``mjcf/``) or any folder holding ``<name>.xml``
and ``machine.toml``, and the name of the application module that implements its commands (imported by
:mod:`pmcal.commands.routing`, the layer above).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from pmcal.errors import InputError
from pmcal.mechanism.machine_spec import MachineSpec
from pmcal.mjcf import ROOT as MJCF_ROOT
from pmcal.mjcf import machine_dir

#: the machine of ``pmcal`` without ``--machine``
DEFAULT_MACHINE = "ocpm_2dof"
#: the seeded machines with application modules of their own, by the ``[machine] kind`` of their TOML
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


def machine_folder(value: str | Path) -> Path:
    """The folder ``value`` names: a built-in name, else a path to a folder with a ``machine.toml``.

    Raises :class:`~pmcal.errors.InputError` (field ``--machine``) for anything else.
    """
    text = str(value)
    if text in builtin_names():
        return machine_dir(text)
    path = Path(text).expanduser()
    if path.is_dir():
        return path                  # MachineSpec.load says what is missing in it
    if path.exists():
        raise InputError(f"{path} is a file; --machine takes a built-in name or a machine folder",
                         field="--machine")
    raise InputError(f"unknown machine '{text}': neither a built-in name ({', '.join(builtin_names())}) nor a "
                     "folder holding NAME.xml and machine.toml", field="--machine")


class Machine:
    """A machine: its validated ``machine.toml`` and MJCF, the application that runs its commands, its
    commands' defaults and (built on first use) its digital twin.

    Attributes
    ----------
    spec : :class:`pmcal.mechanism.machine_spec.MachineSpec`
        The folder's configuration (docs/machine_toml.md): motors, targets, task coordinates, workspace,
        errors, tracker noise, table axes. ``spec.legacy`` for the seeded machines.
    name, folder : the machine's name (``[machine] name``, else the folder's) and its folder.
    app_name : the application module of its commands (:data:`LEGACY_APPS` or :data:`GENERIC_APP`;
        :mod:`pmcal.commands.routing` imports it and gives its commands' defaults and option help).

    Examples
    --------
    >>> m = Machine.builtin("delta_3dof")                        # doctest: +SKIP
    >>> m.spec.motor_columns                                      # doctest: +SKIP
    ('m1_cmd_deg', 'm2_cmd_deg', 'm3_cmd_deg')
    >>> Machine.from_folder("/home/me/my_delta").twin.error_keys   # doctest: +SKIP
    """

    def __init__(self, spec: MachineSpec):
        if spec.legacy and spec.folder != machine_dir(spec.kind).resolve():
            raise InputError(f"a copy of the seeded machine {spec.kind} runs its dedicated code, which reads the "
                             f"built-in folder only (edits here would be ignored): use --machine {spec.kind}",
                             file=str(spec.folder / TOML_NAME), field="machine.kind")
        self.spec = spec
        self.name: str = spec.name
        self.folder: Path = spec.folder
        self.legacy: bool = spec.legacy
        self.app_name = LEGACY_APPS[spec.kind] if spec.legacy else GENERIC_APP
        self._twin = None

    def __repr__(self) -> str:
        return f"Machine({self.name!r}, folder={str(self.folder)!r}, app={self.app_name!r})"

    @classmethod
    def from_folder(cls, folder: str | Path) -> Machine:
        """The machine of a folder holding ``<name>.xml`` and ``machine.toml`` (validated: an
        :class:`~pmcal.errors.InputError` names the file, key and fix)."""
        return cls(MachineSpec.load(folder))

    @classmethod
    def builtin(cls, name: str) -> Machine:
        """A built-in machine by name (:func:`builtin_names`)."""
        if name not in builtin_names():
            raise InputError(f"no built-in machine '{name}' (built-in: {', '.join(builtin_names())})",
                             field="--machine")
        return cls.from_folder(machine_dir(name))

    @classmethod
    def resolve(cls, value: str | Path) -> Machine:
        """The machine ``--machine VALUE`` selects: a built-in name or a folder (:func:`machine_folder`)."""
        return cls.from_folder(machine_folder(value))

    @property
    def twin(self):
        """The closed-chain digital twin (:class:`pmcal.twin.closed_chain.ClosedChainTwin`), compiled on
        first use. The seeded machines have their own twins (``pmcal.twin.ocpm.machine``, ``pmcal.twin.planar``)."""
        if self.legacy:
            raise InputError(f"machine '{self.name}' runs on its dedicated twin, not the closed-chain one",
                             field="--machine")
        if self._twin is None:
            # imported here, not at the top: MuJoCo loads in ~2 s and the parser (pmcal --help) builds a
            # Machine for every call; not a cycle (pmcal.twin is a lower layer)
            from pmcal.twin.closed_chain import ClosedChainTwin

            try:
                self._twin = ClosedChainTwin(self.spec)
            except ValueError as exc:         # MuJoCo's compiler refused the MJCF
                text = "; ".join(line.strip() for line in str(exc).splitlines() if line.strip())
                raise InputError(f"MuJoCo cannot compile the model: {text}{_plugin_hint(text)}",
                                 file=str(self.spec.model_path)) from None
        return self._twin


def _plugin_hint(text: str) -> str:
    """Advice for a model that names an engine plugin this MuJoCo lacks (onshape-to-robot's ``sdf`` option
    writes ``mujoco.sdf.sdflib`` geoms, a plugin the pip wheel does not bundle): pmcal needs no collision
    geometry, so the geoms can be plain meshes. Empty for any other compiler message."""
    found = re.search(r"plugin (\S+) not found", text)
    if not found:
        return ""
    return (f" (this MuJoCo has no plugin {found.group(1)}; pmcal needs no collision geometry: give the geoms "
            "that use it type=\"mesh\" and delete their <plugin instance=.../> and the <extension> that declares "
            "it, or install a MuJoCo built with that plugin)")


def resolve(value: str | Path) -> Machine:
    """The machine ``--machine VALUE`` selects."""
    return Machine.resolve(value)


def file_machine(path: str | Path) -> str | None:
    """The machine a file says it is of, or None: a CSV's ``# pmcal COMMAND: machine NAME`` (or a table's
    ``# machine=NAME``) comment line (pmcal writes one in every file), a JSON's ``mechanism`` or ``machine`` (parameters, tables). Used to say "another
    machine's file" when a file does not fit the selected machine."""
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as fh:
            head = fh.read(64 * 1024)
    except OSError:
        return None
    if head.lstrip().startswith("{"):
        try:
            doc = json.loads(head if len(head) < 64 * 1024 else Path(path).read_text(encoding="utf-8-sig"))
        except (ValueError, OSError, RecursionError):
            return None
        name = doc.get("mechanism") or doc.get("machine") if isinstance(doc, dict) else None
        return name if isinstance(name, str) else None
    if Path(path).suffix.lower() != ".csv":
        return None
    for line in head.splitlines():
        if not line.startswith("#"):
            break
        found = re.match(r"#\s*(?:pmcal\b[^:]*:\s*machine |machine=)([A-Za-z0-9_.-]+)", line)
        if found:
            return found.group(1).rstrip(",.")
    return None
