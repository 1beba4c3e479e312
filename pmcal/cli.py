"""The ``pmcal`` command line.

Subcommands live in :mod:`pmcal.commands`, one module each, with a ``register(subparsers)`` function
that adds its parser and sets ``func`` (a callable taking the parsed namespace and returning an exit
status). This module owns what every command shares:

- ``--quiet`` / ``--verbose`` (accepted before or after the subcommand) and ``--version``;
- one output check before any work (:func:`check_outputs`): unwritable, missing folder, a folder where
  a file goes, a read-only file, a folder pmcal did not write -> exit 2 with one line;
- one line per output on stdout (``pmcal: wrote PATH``), also when piped. An output is a file or folder
  named by an output option or its default (:data:`FILE_OUTPUTS`, :data:`FOLDER_OUTPUTS`, plus the CSV
  written beside a compensation table); a folder (``demo --out``, ``diagnose --report``) is one output,
  ``PATH/``. Analysis commands print their result line before it (``evaluate``, ``diagnose``, ``push``,
  ...); the demos print only the wrote-lines (their summary is a status line: terminal or ``--verbose``);
- ``--quiet`` prints nothing but errors: no result lines, no wrote-lines, no progress (stdout is empty);
- no traceback reaches the user: bad input -> exit 2, failures -> exit 1 with one line (``--verbose``
  adds the traceback), Ctrl-C -> exit 130 with one line.

File formats: ``docs/formats.md``.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import pkgutil
import sys
from pathlib import Path

from pmcal import __version__, progress, threads
from pmcal.errors import InputError, RunError
from pmcal.fileio import check_output

DEFAULT_MACHINE = "ocpm_2dof"

#: (command, attribute) of every file the commands write; folders in :data:`FOLDER_OUTPUTS`
FILE_OUTPUTS: dict[str, tuple[str, ...]] = {
    "identify": ("output",), "compensate": ("output", "table"), "evaluate": ("json",),
    "diagnose": ("json",), "twin measure": ("output",), "twin plan": ("output",), "twin render": ("output",), "targets": ("output",),
    "push": ("json", "audit"), "plc unlock": ("audit",), "loop": ("json",),
}
FOLDER_OUTPUTS: dict[str, tuple[str, ...]] = {"demo": ("out",), "diagnose": ("report",)}
#: (command, attribute) of a file output that brings a second file beside it: suffix of that file
COMPANIONS: dict[tuple[str, str], str] = {("compensate", "table"): ".csv"}

EPILOG = ("File formats (measurement, targets, setpoints, parameters, diagnosis JSON, compensation table): "
          "docs/formats.md. Units at every interface: mm and degrees.")


#: per-machine help: (command, option) -> help text, or None to hide an option that machine does not have
MACHINE_HELP: dict[str, dict[tuple[str, str], str | None]] = {
    "ocpm_2dof": {
        ("twin measure", "--servo-noise"): None, ("identify", "--allow-rank-deficient"): None,
        ("twin measure", "--poses"): "number of poses (default 24)",
        ("identify", "--model"): "error model: whole closed chain (full, default) or the paper's per-limb real "
                                 "IK (paper)",
        ("identify", "--method"): "identification method: --model paper hga (default), ga, pso, sa, lm, "
                                  "tikhonov, tsvd; --model full the whole-chain least squares",
        ("twin measure", "--preset"): "built-in error set: nominal (default) or paper-table2",
        ("twin render", "--preset"): "built-in error set: nominal (default) or paper-table2",
    },
    "planar_2dof": {
        **{("twin measure", o): None for o in ("--stiffness-ratio", "--effect", "--payload", "--temperature",
                                                "--shuffle", "--seconds-per-pose", "--theta-max",
                                                "--no-random-approach", "--tracker-pose", "--nest-error",
                                                "--blocked", "--outliers")},
        **{("identify", o): None for o in ("--frame", "--nest-tolerance", "--robust")},
        ("twin render", "--stiffness-ratio"): None, ("compensate", "--table"): None,
        ("compensate", "--grid"): None, ("compensate", "--table-version"): None,
        ("twin measure", "--poses"): "number of positions on the workspace boundary, even, >= 6 (default 6, "
                                     "the paper's)",
        ("twin measure", "--noise"): "linear-scale noise, standard deviation, mm (default the paper's eq. 34)",
        ("twin measure", "--targets"): "explicit target positions (x_mm, y_mm) instead of the boundary layout",
        ("twin measure", "--preset"): "built-in error set: nominal (default) or group1..group6 (the paper's "
                                      "Table 3 groups)",
        ("twin render", "--preset"): "built-in error set: nominal (default) or group1..group6",
        ("twin render", "--pose"): "position X,Y of the platform, mm (seed frame, y < 0)",
        ("identify", "--model"): "error model: the paper's 4 parameters (simplified = paper, default) or all "
                                 "12 (full; rank 9, see --allow-rank-deficient)",
        ("identify", "--method"): "tsvd (default, eq. 29), ls (eq. 25) or gls (whitened TSVD)",
        ("identify", "--sigma"): "linear-scale noise, mm (default the paper's eq. 34)",
        ("identify", "--seed"): None,
        ("compensate", "--targets"): "targets CSV: x_mm, y_mm ('pmcal --machine planar_2dof targets' writes "
                                     "one)",
        ("compensate", "-o"): "setpoints CSV to write: the targets with theta1_deg, theta2_deg appended",
    },
}


def _machine_from_argv(argv: list[str]) -> str:
    """The ``--machine`` value before the subcommand (for per-machine help), else the default."""
    for i, a in enumerate(argv):
        if a == "--machine" and i + 1 < len(argv):
            return argv[i + 1]
        if a.startswith("--machine="):
            return a.split("=", 1)[1]
    return DEFAULT_MACHINE


def specialise_help(parser: argparse.ArgumentParser, machine: str) -> None:
    """Help texts of ``machine``: its own wording and defaults, options of other machines hidden."""
    table = MACHINE_HELP.get(machine, {})
    for name, sp in _named_subparsers(parser):
        for action in sp._actions:
            for opt in action.option_strings:
                if (name, opt) in table:
                    text = table[(name, opt)]
                    action.help = argparse.SUPPRESS if text is None else text
        if machine != DEFAULT_MACHINE:
            sp.description = f"(machine {machine}) " + (sp.description or "")


def _named_subparsers(parser: argparse.ArgumentParser, prefix: str = ""):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sp in action.choices.items():
                full = f"{prefix}{name}"
                yield full, sp
                yield from _named_subparsers(sp, full + " ")


def _common_options(p: argparse.ArgumentParser, top: bool) -> None:
    """``--quiet``/``--verbose`` on the top parser and, defaults suppressed, on every subcommand."""
    kw = {} if top else {"default": argparse.SUPPRESS}
    p.add_argument("--quiet", "-q", action="store_true",
                   help="print nothing but errors: no results, no 'wrote' lines, no progress", **kw)
    p.add_argument("--verbose", "-v", action="store_true",
                   help="more detail (and the traceback of an unexpected failure)", **kw)


def build_parser(machine: str = DEFAULT_MACHINE) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pmcal",
        description="Calibrate parallel mechanisms against a MuJoCo digital twin and push the "
                    "compensation to the PLC. Units at every interface: mm and degrees.",
        epilog=EPILOG)
    parser.add_argument("--version", action="version", version=f"pmcal {__version__}",
                        help="print the version and exit")
    parser.add_argument("--machine", default=DEFAULT_MACHINE, metavar="NAME",
                        help=f"machine: ocpm_2dof or planar_2dof (a folder under mjcf/); default "
                             f"{DEFAULT_MACHINE}. 'pmcal --machine NAME COMMAND --help' shows that machine's "
                             "options and defaults")
    _common_options(parser, top=True)       # --quiet: nothing on stdout, errors only on stderr
    parser.add_argument("--blas-threads", type=int, default=None, metavar="N",
                        help="BLAS threads per process (default: $PMCAL_BLAS_THREADS, else 1; 0 = the "
                             "libraries' own default); see docs/speed.md")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    import pmcal.commands as commands
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda i: i.name):
        module = importlib.import_module(f"pmcal.commands.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(sub)
    for _, sp in _named_subparsers(parser):
        if not any("--quiet" in a.option_strings for a in sp._actions):
            _common_options(sp, top=False)
        if sp.epilog is None:
            sp.epilog = EPILOG
    specialise_help(parser, machine)
    return parser


def _command_name(args) -> str:
    sub = getattr(args, "twin_command", None) or getattr(args, "plc_cmd", None)
    return f"{args.command} {sub}" if sub else str(args.command)


def output_paths(args) -> list[tuple[str, str, bool]]:
    """(option, path, is_folder) of every output the parsed command will write."""
    name = _command_name(args)
    out = []
    for attrs, folder in ((FILE_OUTPUTS.get(name, ()), False), (FOLDER_OUTPUTS.get(name, ()), True)):
        for attr in attrs:
            value = getattr(args, attr, None)
            if value:
                option = "--" + attr.replace("_", "-") if attr != "output" else "-o"
                out.append((option, str(value), folder))
                suffix = COMPANIONS.get((name, attr))
                if suffix and not folder:
                    out.append((option, str(Path(str(value)).with_suffix(suffix)), False))
    return out


def check_outputs(args) -> None:
    """The one output check, before any work starts."""
    force = bool(getattr(args, "force", False))
    seen = set()
    for option, path, folder in output_paths(args):
        key = os.path.abspath(path)
        if key in seen:
            raise InputError(f"{path} is given as two outputs", field=option)
        seen.add(key)
        try:
            check_output(path, folder=folder, force=force, field=option)
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


def main(argv: list[str] | None = None) -> int:
    """Run one pmcal command line; returns the exit status. The display settings (``--quiet``,
    ``--verbose``, a long job) last for this call only."""
    try:
        return _main(argv)
    finally:
        progress.set_quiet(False)
        progress.set_verbose(False)
        progress.set_long(False)


def _main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(_machine_from_argv(argv))
    try:
        args = parser.parse_args(argv)
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
        print(f"pmcal: error: {exc}", file=sys.stderr)
        return 2
    except RunError as exc:
        print(f"pmcal: failed: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("pmcal: interrupted; nothing half-written", file=sys.stderr)
        return 130
    except MemoryError:
        print("pmcal: failed: out of memory (input too large?)", file=sys.stderr)
        return 1
    except OSError as exc:           # a file the command needed could not be read or written
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"pmcal: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    except Exception as exc:         # noqa: BLE001 -- last resort: one line, never a traceback
        if verbose:
            import traceback
            traceback.print_exc()
        print(f"pmcal: failed: {type(exc).__name__}: {exc} (a bug: please report it with --verbose output)",
              file=sys.stderr)
        return 1


def run() -> None:  # pragma: no cover -- console script entry point
    """Entry point of the console script: Ctrl-C during imports also ends with one line."""
    try:
        status = main()
    except KeyboardInterrupt:
        print("pmcal: interrupted", file=sys.stderr)
        status = 130
    sys.exit(status)


if __name__ == "__main__":  # pragma: no cover
    run()
