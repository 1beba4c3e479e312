"""The ``pmcal`` command line.

Subcommands live in :mod:`pmcal.commands`, one module each, with a ``register(subparsers)`` function
that adds its parser and sets ``func`` (a callable taking the parsed namespace and returning an exit
status). This module owns what every command shares:

- ``--quiet`` / ``--verbose`` (accepted before or after the subcommand) and ``--version``;
- one output check before any work (:func:`check_outputs`): unwritable, missing folder, a folder where
  a file goes, a read-only file, a folder pmcal did not write, a name without its format's suffix, an
  output that is one of the command's inputs (:data:`FILE_INPUTS`) -> exit 2 with one line;
- one line per output on stdout (``pmcal: wrote PATH``), also when piped. An output is a file or folder
  named by an output option or its default (:data:`FILE_OUTPUTS`, :data:`FOLDER_OUTPUTS`, plus the CSV
  written beside a compensation table); a folder (``demo --out``, ``diagnose --report``) is one output,
  ``PATH/``. Commands print their result line before it (``identify``, ``evaluate``, ``diagnose``,
  ``push``, the demos, ...), also when piped;
- ``--quiet`` prints nothing but errors: no result lines, no wrote-lines, no progress (stdout is empty);
- no traceback reaches the user: bad input -> exit 2, failures -> exit 1 with one line (``--verbose``
  adds the traceback), Ctrl-C -> exit 130 with one line, SIGTERM the same clean-up and exit 143.

File formats: ``docs/formats.md``.
"""

from __future__ import annotations

import sys

try:                     # the console script imports this module before run() can catch a Ctrl-C: 0.4 s of imports
    import argparse
    import contextlib
    import importlib
    import os
    import pkgutil
    import signal
    import threading
    from pathlib import Path

    from pmcal import __version__, machines, progress, threads
    from pmcal.commands.options import CommandSet
    from pmcal.commands.routing import option_help
    from pmcal.errors import InputError, RunError
    from pmcal.fileio import check_output
    from pmcal.option_ranges import check_ranges
except KeyboardInterrupt:
    print("pmcal: interrupted", file=sys.stderr)
    raise SystemExit(130) from None

DEFAULT_MACHINE = machines.DEFAULT_MACHINE

EPILOG = ("File formats (measurement, targets, setpoints, parameters, diagnosis JSON, compensation table): "
          "docs/formats.md. Units at every interface: mm and degrees.")


def _machine_from_argv(argv: list[str]) -> str:
    """The ``--machine`` value (a built-in name or a folder), read by a pre-parser before the parser of
    that machine is built; the default machine without one."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--machine", default=DEFAULT_MACHINE)
    known, _ = pre.parse_known_args(argv)
    return known.machine


def _named_subparsers(parser: argparse.ArgumentParser):
    """(full command name, parser) of every (sub)command of a parser made by :func:`build_parser`."""
    for name, cmd in parser.pmcal_commands.items():
        yield name, cmd.parser


class OneLineParser(argparse.ArgumentParser):
    """argparse's parser whose usage error is one line (the command, what is wrong, where the help is)
    instead of the usage block and the error: every bad input gets one line."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} ('{self.prog} --help' lists the options)\n")


def _common_options(p, top: bool) -> None:
    """``--quiet``/``--verbose`` on the top parser and, defaults suppressed, on every subcommand."""
    kw = {} if top else {"default": argparse.SUPPRESS}
    p.add_argument("--quiet", "-q", action="store_true",
                   help="print nothing but errors: no results, no 'wrote' lines, no progress", **kw)
    p.add_argument("--verbose", "-v", action="store_true",
                   help="more detail (and the traceback of an unexpected failure)", **kw)


def _finish_command(cmd) -> None:
    """What every subcommand shares: ``--quiet``/``--verbose`` (unless it has its own) and the epilog."""
    if "--quiet" not in cmd.flags:
        _common_options(cmd, top=False)
    if cmd.parser.epilog is None:
        cmd.parser.epilog = EPILOG


def build_parser(machine: str = DEFAULT_MACHINE) -> argparse.ArgumentParser:
    """The ``pmcal`` parser for ``machine`` (a built-in name or a machine folder): its commands' options
    worded for that machine (its application's ``option_help``), the options it does not have (their
    ``kinds=``) refused. ``parser.pmcal_commands`` maps every full command name to its
    :class:`pmcal.commands.options.Command`; ``selected_machine`` in the parsed namespace is the
    :class:`pmcal.machines.Machine`."""
    selected = machines.resolve(machine)
    parser = OneLineParser(
        # the machine in every usage line and in the '--help' hint of a usage error: the help that applies
        prog="pmcal" if machine == DEFAULT_MACHINE else f"pmcal --machine {machine}",
        description="Calibrate parallel mechanisms against a MuJoCo digital twin and push the "
                    "compensation to the PLC. Units at every interface: mm and degrees.",
        epilog=EPILOG)
    parser.add_argument("--version", action="version", version=f"pmcal {__version__}",
                        help="print the version and exit")
    parser.add_argument("--machine", default=DEFAULT_MACHINE, metavar="NAME|DIR",
                        help=f"machine: a built-in name ({', '.join(machines.builtin_names())}: folders under "
                             "mjcf/) or the path of a folder holding NAME.xml and machine.toml "
                             f"(docs/ADDING_A_MACHINE.md); default {DEFAULT_MACHINE}. "
                             "'pmcal --machine NAME COMMAND --help' shows that machine's options and defaults")
    _common_options(parser, top=True)       # --quiet: nothing on stdout, errors only on stderr
    parser.add_argument("--blas-threads", type=int, default=None, metavar="N",
                        help="BLAS threads per process (default: $PMCAL_BLAS_THREADS, else 1; 0 = the "
                             "libraries' own default); see docs/speed.md")
    record: dict = {}
    describe = "" if selected.name == DEFAULT_MACHINE else f"(machine {selected.name}) "
    commands = CommandSet(parser.add_subparsers(dest="command", metavar="COMMAND"), option_help(selected),
                          record, selected.spec.kind, selected.name, _finish_command, describe=describe)
    import pmcal.commands as command_modules
    for info in sorted(pkgutil.iter_modules(command_modules.__path__), key=lambda i: i.name):
        module = importlib.import_module(f"pmcal.commands.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(commands)
    commands.finish_all()
    # every command's file options with their roles, as the command declared them (commands.options.FileRole)
    parser.set_defaults(selected_machine=selected, pmcal_files={name: cmd.files for name, cmd in record.items()})
    parser.pmcal_commands = record
    return parser


def _command_name(args) -> str:
    sub = getattr(args, "twin_command", None) or getattr(args, "plc_cmd", None)
    return f"{args.command} {sub}" if sub else str(args.command)


def _files(args) -> dict:
    """attribute -> :class:`pmcal.commands.options.FileRole` of the parsed command's file options."""
    return getattr(args, "pmcal_files", {}).get(_command_name(args), {})


def output_paths(args, suffixes: bool = False) -> list:
    """(option, path, is_folder) of every output the parsed command will write; with ``suffixes``,
    (option, path, is_folder, the suffixes its format may have or (), the start of a side file of pmcal's
    or None). From the roles the command declared (``role="output"``/``"folder"``)."""
    out = []
    for attr, f in _files(args).items():
        value = getattr(args, attr, None)
        if f.role == "input" or value is None:      # "" is an output: refused by the guard, not taken for none
            continue
        folder = f.role == "folder"
        out.append((f.label, str(value), folder, f.suffixes, None))
        if f.companion and not folder and Path(str(value)).name:     # '', '.', '/': refused by the guard
            suffix, module = f.companion
            start = importlib.import_module(module).SIDE_FILE_START if suffixes else None
            out.append((f.label, str(Path(str(value)).with_suffix(suffix)), False, (), start))
    return out if suffixes else [o[:3] for o in out]


def input_paths(args) -> list[tuple[str, str]]:
    """(option or argument name, path) of every file the parsed command reads (``role="input"``)."""
    return [(f.label, str(getattr(args, attr))) for attr, f in _files(args).items()
            if f.role == "input" and getattr(args, attr, None)]


def check_outputs(args) -> None:
    """The one output check, before any work starts."""
    seen = set()
    inputs = input_paths(args)
    machine = getattr(args, "selected_machine", None)
    machine_folder = getattr(machine, "folder", None)
    for option, path, folder, suffixes, own in output_paths(args, suffixes=True):
        key = os.path.abspath(path)
        if key in seen:
            raise InputError(f"{path} is given as two outputs", field=option)
        seen.add(key)
        try:
            check_output(path, folder=folder, field=option, suffixes=suffixes, inputs=inputs,
                         machine_folder=machine_folder, own=own)
        except InputError as exc:       # checked before any work: say so
            raise InputError(f"{exc.message}; nothing was sent or written", field=exc.field) from None


def _report_written(args, before: dict[str, float | None]) -> None:
    for option, path, folder in output_paths(args):
        p = Path(path)
        if p.exists() and (before.get(path) is None or p.stat().st_mtime_ns != before[path]):
            print(f"pmcal: wrote {path}{'/' if folder else ''}", flush=True)


def _mtime(path: str) -> float | None:
    try:
        return Path(path).stat().st_mtime_ns
    except OSError:
        return None


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the program is, like Ctrl-C's KeyboardInterrupt: every clean-up that Ctrl-C
    runs (staging folders, temporary files, worker processes) runs for it too."""


#: exit status after SIGTERM: what a shell reports for a command the signal ended
TERMINATED_STATUS = 128 + signal.SIGTERM


def _terminate(signum, frame):
    raise Terminated()


def main(argv: list[str] | None = None) -> int:
    """Run one pmcal command line; returns the exit status. The display settings (``--quiet``,
    ``--verbose``, a long job) last for this call only; SIGTERM is handled as Ctrl-C is during it (exit
    143 instead of 130)."""
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        return _main(argv)
    except Terminated as stop:          # between the command's own handlers
        return _stopped(stop)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        progress.set_quiet(False)
        progress.set_verbose(False)
        progress.set_long(False)


def _join_negative_lists(argv: list[str]) -> list[str]:
    """``--grid -5,10`` as ``--grid=-5,10``: argparse takes a value starting with '-' and holding a comma
    for an option, and would answer with its own usage error instead of ours naming the option."""
    out: list[str] = []
    for a in argv:
        if (out and out[-1].startswith("--") and "=" not in out[-1] and len(a) > 1 and a[0] == "-"
                and (a[1].isdigit() or a[1] == ".") and "," in a):
            out[-1] = f"{out[-1]}={a}"
        else:
            out.append(a)
    return out


def _main(argv: list[str] | None = None) -> int:
    argv = _join_negative_lists(sys.argv[1:] if argv is None else list(argv))
    try:
        parser = build_parser(_machine_from_argv(argv))
    except InputError as exc:            # a --machine that is no machine
        print(f"pmcal: error: {exc}", file=sys.stderr)
        return 2
    try:
        args = parser.parse_args(argv)
    except Terminated:
        raise
    except KeyboardInterrupt:
        print("pmcal: interrupted", file=sys.stderr)
        return 130
    verbose = bool(getattr(args, "verbose", False))
    quiet = bool(getattr(args, "quiet", False))
    progress.set_quiet(quiet)
    progress.set_verbose(verbose and not quiet)
    progress.set_long(False)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    try:
        threads.apply_blas_policy(args.blas_threads)
    except ValueError as exc:
        print(f"pmcal: error: {exc}", file=sys.stderr)
        return 2
    try:
        check_ranges(args)
        prepare = getattr(args, "prepare", None)
        if prepare is not None:
            prepare(args)
        check_outputs(args)
        before = {path: _mtime(path) for _, path, _ in output_paths(args)}
        with open(os.devnull, "w") if quiet else contextlib.nullcontext() as sink:
            with contextlib.redirect_stdout(sink) if quiet else contextlib.nullcontext():
                status = int(args.func(args) or 0)
        if status == 0 and not quiet:
            _report_written(args, before)
        return status
    except InputError as exc:
        print(f"pmcal: error: {_name_other_machine(exc, args)}", file=sys.stderr)
        return 2
    except RunError as exc:
        print(f"pmcal: failed: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt as stop:    # Ctrl-C, or SIGTERM (Terminated)
        return _stopped(stop)
    except MemoryError:
        print("pmcal: failed: out of memory (input too large?)", file=sys.stderr)
        return 1
    except BrokenPipeError:          # the reader of stdout went away (pmcal ... | head): stop quietly
        _silence_stdout()
        return BROKEN_PIPE_STATUS
    except OSError as exc:           # a file the command needed could not be read or written
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"pmcal: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    except Exception as exc:         # noqa: BLE001 -- last resort: one line, never a traceback
        stop = _interruption(exc)
        if stop is not None:         # Ctrl-C inside an extension's import: MuJoCo re-raises it as ImportError
            return _stopped(stop)
        if verbose:
            import traceback
            traceback.print_exc()
        print(f"pmcal: failed: {type(exc).__name__}: {exc} (a bug: please report it with --verbose output)",
              file=sys.stderr)
        return 1


def _stopped(stop: KeyboardInterrupt) -> int:
    """The line and exit status of a command stopped by Ctrl-C (130) or SIGTERM (:class:`Terminated`, 143)."""
    if isinstance(stop, Terminated):
        print("pmcal: terminated; nothing half-written", file=sys.stderr)
        return TERMINATED_STATUS
    print("pmcal: interrupted; nothing half-written", file=sys.stderr)
    return 130


def _interruption(exc: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C (or SIGTERM) that caused ``exc``, if one did: an extension module whose initialisation is
    interrupted (``import mujoco`` takes a second) raises ``ImportError: initialization failed`` from the
    KeyboardInterrupt, which is the user's stop, not a bug."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def _name_other_machine(exc: InputError, args) -> InputError:
    """A file that does not fit the selected machine and says it is another machine's
    (:func:`pmcal.machines.file_machine`): the real cause, named, instead of the first check it failed."""
    machine = getattr(args, "selected_machine", None)
    other = machines.file_machine(exc.file) if exc.file and machine is not None else None
    if other is None or other == machine.name:
        return exc
    return InputError(f"this is a file of machine {other} (it says so), not of {machine.name}: give --machine "
                      f"{other} or a file of {machine.name} (what did not fit: {exc.message})", file=exc.file,
                      field=exc.field)


#: exit status when stdout's reader closed the pipe: what a shell reports for a command SIGPIPE ended
BROKEN_PIPE_STATUS = 128 + 13


def _silence_stdout() -> None:
    """Point stdout at /dev/null, so the interpreter's last flush does not fail on the closed pipe again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):     # stdout is no file (captured by a test)
        pass


def run(loading_handler=None) -> None:
    """Entry point of the console script (``pmcal``, through :func:`pmcal.console.run`): :func:`main`; Ctrl-C
    ends with one line (exit 130), a closed stdout (``pmcal ... | head``) with none (exit 141), never with a
    traceback. ``loading_handler``: the SIGINT handler that stopped the process while the command line
    loaded (:mod:`pmcal.console`); Python's own is put back in its place, inside the handling below."""
    try:
        if loading_handler is not None and signal.getsignal(signal.SIGINT) is loading_handler:
            signal.signal(signal.SIGINT, signal.default_int_handler)
        status = main()
        sys.stdout.flush()
    except Terminated:
        print("pmcal: terminated", file=sys.stderr)
        status = TERMINATED_STATUS
    except KeyboardInterrupt:
        print("pmcal: interrupted", file=sys.stderr)
        status = 130
    except BrokenPipeError:
        _silence_stdout()
        status = BROKEN_PIPE_STATUS
    sys.exit(status)


if __name__ == "__main__":  # pragma: no cover
    run()
