"""The subcommands' parsers built for one machine, from data, through argparse's public API only.

Each command module's ``register(commands)`` adds its parsers with :meth:`CommandSet.add_parser` and
their options with :meth:`Command.add_argument`, exactly as with argparse, giving the generic help
text. An option that only some machines have says which where it is added: ``kinds=`` the
``[machine] kind`` values of machine.toml that have it (``"ocpm_2dof"``, ``"planar_2dof"``, ``"chain"``: every
machine folder); on any other machine the option is refused, in one line naming the machine and the kinds
that have it (exit 2), and it is not in ``--help``. The selected machine's application module supplies a table
of help texts (``option_help``): ``(command, option) -> text`` rewords an option for that machine,
``-> {"help": ..., "metavar": ..., "default": ...}`` changes further keywords of ``add_argument``.
``command`` is the full command name (``"twin measure"``), ``option`` any of the option's flags (``"-o"`` or
``"--output"``) or a positional's name; the key ``(command, "")`` rewords the command's own one-line help.

An option that names a file declares its **role** where it is added (``role="input"``, ``"output"`` or
``"folder"``; an output's ``suffixes`` and its ``companion``, the file written beside it): the command line
derives every file check from these (:class:`FileRole`; ``pmcal.cli.check_outputs``: no output may be an
input, an output's suffix, a side file replaced only if it is pmcal's), so a command's facts live where the
command is declared.

Example::

    commands = CommandSet(parser.add_subparsers(dest="command"), table={("identify", "--sigma"): "noise, mm"},
                          record={}, kind="chain", machine="my_delta")
    p = commands.add_parser("identify", help="calibrate")
    p.add_argument("--sigma", type=float, help="tracker noise")             # worded "noise, mm" here
    p.add_argument("--robust", action="store_true", help="robust fit", kinds=("ocpm_2dof",))  # refused here
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from pmcal.mechanism.machine_spec import LEGACY_KINDS

HelpTable = Mapping[tuple[str, str], "str | dict"]
#: every ``[machine] kind`` an option's ``kinds=`` may name
KINDS = ("chain",) + tuple(LEGACY_KINDS)
#: how a message names the machines of a ``[machine] kind``
KIND_NAMES = {"chain": "machine folders"}


class NotForThisMachine(argparse.Action):
    """An option the selected machine does not have (its ``kinds=``): taking it is a usage error naming the
    machine and the kinds that have it. It takes the values the option would (``nargs``), so the message is
    about the option, not about a value left over."""

    def __init__(self, option_strings, dest, machine: str = "", kinds: tuple[str, ...] = (), **kwargs):
        self.machine, self.kinds = machine, kinds
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        names = [KIND_NAMES.get(k, k) for k in self.kinds]
        parser.error(f"{option_string} is not an option of machine {self.machine}: only "
                     f"{' and '.join(names)} {'have' if len(names) > 1 or names[0].endswith('s') else 'has'} it")


@dataclass(frozen=True)
class FileRole:
    """What a file option of a command is: ``role`` ``"input"`` (read), ``"output"`` (a file written) or
    ``"folder"`` (a folder written); ``label`` how the user names it (a positional's metavar, else its
    option); an output's ``suffixes`` (its format's, case-insensitive; any when empty) and ``companion``:
    (suffix, module) of the file written beside it, whose ``SIDE_FILE_START`` is the text such a file of
    pmcal's starts with (imported when needed, so ``--help`` does not import MuJoCo)."""

    role: str
    label: str
    suffixes: tuple[str, ...] = ()
    companion: tuple[str, str] | None = None


class Command:
    """One (sub)command's parser: ``add_argument`` with the machine's wording; ``parser`` is the
    :class:`argparse.ArgumentParser` itself, ``flags`` every option string added."""

    def __init__(self, parser: argparse.ArgumentParser, name: str, owner: CommandSet, target=None,
                 flags: set[str] | None = None, files: dict[str, FileRole] | None = None):
        self.parser, self.name, self.owner = parser, name, owner
        self._target = parser if target is None else target
        self.flags: set[str] = set() if flags is None else flags
        #: attribute -> :class:`FileRole` of every file option of this command
        self.files: dict[str, FileRole] = {} if files is None else files

    def _text(self, keys, default: str | None):
        table = self.owner.table
        for key in keys:
            if (self.name, key) in table:
                return table[(self.name, key)]
        return default

    def add_argument(self, *flags: str, help: str, role: str | None = None, suffixes: tuple[str, ...] = (),
                     companion: tuple[str, str] | None = None, kinds: tuple[str, ...] | None = None, **kwargs):
        """:meth:`argparse.ArgumentParser.add_argument` with the machine's help text. ``kinds``: the
        ``[machine] kind`` values that have this option (default: every machine); on another machine the
        option is refused (:class:`NotForThisMachine`) and None is returned. ``role``, ``suffixes``,
        ``companion``: a file option's :class:`FileRole`."""
        if kinds is not None and not set(kinds) <= set(KINDS):
            raise ValueError(f"unknown machine kind in {kinds!r} (known: {', '.join(KINDS)})")
        if kinds is not None and self.owner.kind not in kinds:
            nargs = 0 if kwargs.get("action") in ("store_true", "store_false") else kwargs.get("nargs")
            self._target.add_argument(*flags, action=NotForThisMachine, nargs=nargs, help=argparse.SUPPRESS,
                                      default=argparse.SUPPRESS, machine=self.owner.machine, kinds=tuple(kinds))
            return None
        text = self._text(flags, help)
        if isinstance(text, dict):           # wording and other keywords (metavar, ...)
            kwargs = {**kwargs, **text}
            text = kwargs.pop("help", help)
        self.flags.update(flags)
        action = self._target.add_argument(*flags, help=text, **kwargs)
        if role is not None:
            if role not in ("input", "output", "folder"):
                raise ValueError(f"unknown file role {role!r}")
            positional = not flags[0].startswith("-")
            label = (action.metavar or flags[0]) if positional else \
                ("-o" if "-o" in flags and role != "input" else next(f for f in flags if f.startswith("--")))
            self.files[action.dest] = FileRole(role, label, tuple(suffixes), companion)
        return action

    def add_mutually_exclusive_group(self, **kwargs) -> Command:
        """A group whose options are added as this command's (same table, same ``flags``)."""
        group = self._target.add_mutually_exclusive_group(**kwargs)
        return Command(self.parser, self.name, self.owner, group, self.flags, self.files)

    def add_subparsers(self, **kwargs) -> CommandSet:
        """Sub-commands of this command (``twin measure``): a :class:`CommandSet` named after it."""
        kwargs.setdefault("parser_class", type(self.parser))
        o = self.owner
        return CommandSet(self.parser.add_subparsers(**kwargs), o.table, o.record, o.kind, o.machine, o.finish,
                          prefix=f"{self.name} ", describe=o.describe)

    def set_defaults(self, **kwargs) -> None:
        self.parser.set_defaults(**kwargs)


class CommandSet:
    """The sub-commands of one parser level for one machine: ``kind`` its ``[machine] kind`` (which options
    it has), ``machine`` its name (in messages), ``table`` its wording (:data:`HelpTable`). ``record``
    collects every command by full name (``"twin measure"``) in order of creation; ``finish`` runs on each
    once all are registered."""

    def __init__(self, action, table: HelpTable, record: dict[str, Command], kind: str, machine: str,
                 finish: Callable[[Command], None] | None = None, prefix: str = "", describe: str = ""):
        self.action, self.table, self.record, self.finish = action, table, record, finish
        self.kind, self.machine = kind, machine
        self.prefix, self.describe = prefix, describe

    def add_parser(self, name: str, **kwargs) -> Command:
        """``add_parser`` of :meth:`argparse.ArgumentParser.add_subparsers` with the machine's wording of ``help``; the
        description starts with ``describe`` (the machine, when not the default one)."""
        full = self.prefix + name
        if "help" in kwargs and (full, "") in self.table:
            kwargs["help"] = self.table[(full, "")]
        description = kwargs.pop("description", None) or ""
        if self.describe or description:
            kwargs["description"] = self.describe + description
        cmd = Command(self.action.add_parser(name, **kwargs), full, self)
        self.record[full] = cmd
        return cmd

    def finish_all(self) -> None:
        """Run ``finish`` on every command registered (options every command shares, epilog)."""
        if self.finish is not None:
            for cmd in self.record.values():
                self.finish(cmd)
