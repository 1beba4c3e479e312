"""Top-level commands that every machine implements in its application module:
``demo``, ``identify``, ``compensate``, ``evaluate``, ``diagnose``."""

from __future__ import annotations

import argparse

from pmcal.machines import dispatch


def _cmd(name: str):
    return lambda args: dispatch(name, args)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="the whole job on the built-in machine, no arguments needed")
    p.add_argument("--out", default="pmcal-demo", help="output folder (report, tables); default pmcal-demo")
    p.add_argument("--seed", type=int, default=1, help="random seed of the virtual campaign")
    p.add_argument("--full", action="store_true",
                   help="run the population methods (ga, pso, sa) to their own stopping rules instead of the "
                        "quick demo's capped budgets (about a minute longer)")
    p.add_argument("--hidden-effect", default=None, metavar="NAME",
                   help="hide a physical effect in the campaign and let the diagnosis find it")
    p.set_defaults(func=_cmd("demo"))

    p = sub.add_parser("identify", help="calibrate from a measurement file")
    p.add_argument("measurements", metavar="MEAS.csv")
    p.add_argument("-o", "--output", required=True, metavar="PARAMS.json")
    p.add_argument("--method", default=None, help="identification method (machine default if omitted)")
    p.add_argument("--model", default=None, choices=["full", "paper"],
                   help="error model: whole closed chain (full) or the paper's per-limb real IK (paper)")
    p.add_argument("--sigma", type=float, default=None, help="tracker noise, mm (machine default)")
    p.add_argument("--seed", type=int, default=0, help="random seed of stochastic methods")
    p.add_argument("--frame", default="base", metavar="base|tracker|tracker:T.json",
                   help="frame of the measured targets: the machine's base frame (default) or the tracker's "
                        "own frame (registration and nest offsets identified; T.json: start registration "
                        "{\"R\": 3x3, \"t_mm\": [x, y, z]}), docs/tracker_frame.md")
    p.add_argument("--nest-tolerance", type=float, default=None, metavar="MM",
                   help="prior of the target nests' offsets from the drawing, mm per coordinate (default 0.5)")
    p.add_argument("--robust", action="store_true",
                   help="robust fit with named outlier rejection also in the base frame (always on with "
                        "--frame tracker or blocked targets)")
    p.set_defaults(func=_cmd("identify"))

    p = sub.add_parser("compensate", help="corrected motor commands for target orientations")
    p.add_argument("params", metavar="PARAMS.json")
    p.add_argument("--targets", required=False, metavar="TARGETS.csv")
    p.add_argument("-o", "--output", required=False, metavar="SETPOINTS.csv")
    p.add_argument("--table", default=None, metavar="TABLE.json",
                   help="also write the 2-D compensation table (JSON; CSV beside it)")
    p.add_argument("--grid", default=None, metavar="NPHI,NTHETA", help="table grid size")
    p.add_argument("--table-version", type=int, default=None, metavar="N",
                   help="table version (1..2**32-1, must increase on the PLC); default: Unix time")
    p.set_defaults(func=_cmd("compensate"))

    p = sub.add_parser("evaluate", help="pointing error of a parameter set against a measurement file")
    p.add_argument("params", metavar="PARAMS.json")
    p.add_argument("measurements", metavar="MEAS.csv")
    p.add_argument("--json", default=None, metavar="OUT.json")
    p.set_defaults(func=_cmd("evaluate"))

    p = sub.add_parser("diagnose", help="find, name and add the effect the model misses")
    p.add_argument("measurements", metavar="MEAS.csv")
    p.add_argument("--json", required=True, metavar="OUT.json")
    p.add_argument("--params", default=None, metavar="P.json")
    p.add_argument("--model", default="full", choices=["full", "paper"])
    p.add_argument("--report", default=None, metavar="DIR")
    p.add_argument("--sigma", type=float, default=None, help="tracker noise, mm (else estimated)")
    p.set_defaults(func=_cmd("diagnose"))
