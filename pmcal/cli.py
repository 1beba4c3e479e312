"""The ``pmcal`` command line.

Subcommands live in :mod:`pmcal.commands`, one module each, with a ``register(subparsers)`` function
that adds its parser and sets ``func`` (a callable taking the parsed namespace and returning an exit
status). Bad input raises :class:`pmcal.errors.InputError`, printed here as one line, exit status 2.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from pmcal import __version__, progress, threads
from pmcal.errors import InputError, RunError

DEFAULT_MACHINE = "ocpm_2dof"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pmcal",
        description="Calibrate parallel mechanisms against a MuJoCo digital twin and push the "
                    "compensation to the PLC. Units at every interface: mm and degrees.")
    parser.add_argument("--version", action="version", version=f"pmcal {__version__}")
    parser.add_argument("--machine", default=DEFAULT_MACHINE,
                        help=f"machine name (a folder under mjcf/); default {DEFAULT_MACHINE}")
    parser.add_argument("--quiet", "-q", action="store_true", help="no progress output")
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
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    progress.set_quiet(args.quiet)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    try:
        threads.apply_blas_policy(args.blas_threads)
    except ValueError as exc:
        print(f"pmcal: error: {exc}", file=sys.stderr)
        return 2
    try:
        return int(args.func(args) or 0)
    except InputError as exc:
        print(f"pmcal: error: {exc}", file=sys.stderr)
        return 2
    except RunError as exc:
        print(f"pmcal: failed: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
