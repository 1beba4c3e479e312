"""Top-level commands that every machine implements in its application module:
``demo``, ``identify``, ``compensate``, ``evaluate``, ``diagnose``."""

from __future__ import annotations

from pmcal.commands.options import CommandSet
from pmcal.commands.routing import dispatch


def _cmd(name: str):
    return lambda args: dispatch(name, args)


def _demo_defaults(args) -> None:
    """The demo's folder: ``pmcal-demo``, or ``pmcal-demo-hidden`` for the hidden-effect demo, so one
    never replaces the other's report."""
    if args.out is None:
        args.out = "pmcal-demo-hidden" if getattr(args, "hidden_effect", None) else "pmcal-demo"   # folder machines: no --hidden-effect


def register(sub: CommandSet) -> None:
    p = sub.add_parser("demo", help="the whole job on the built-in machine, no arguments needed")
    p.add_argument("--out", default=None, metavar="DIR", role="folder",
                   help="output folder (report, tables), replaced as a whole; default pmcal-demo. A folder "
                        "holding files pmcal did not write is refused")
    p.add_argument("--force", action="store_true",
                   help="accepted for old scripts; changes nothing: a folder holding files pmcal did not write "
                        "(the working folder, a machine folder, yours) is never replaced")
    p.add_argument("--seed", type=int, default=1, help="random seed of the virtual campaign (default 1)")
    p.add_argument("--full", action="store_true", kinds=("ocpm_2dof",),
                   help="run the population methods (ga, pso, sa) to their own stopping rules instead of the "
                        "quick demo's capped budgets (about a minute longer)")
    p.add_argument("--hidden-effect", default=None, metavar="NAME", kinds=("ocpm_2dof",),
                   help="hide a physical effect in the campaign and let the diagnosis find it: an effect name "
                        "of docs/effects.md or 'random'")
    p.set_defaults(func=_cmd("demo"), prepare=_demo_defaults)

    p = sub.add_parser("identify", help="calibrate from a measurement file")
    p.add_argument("measurements", metavar="MEAS.csv", help="measurement CSV (columns: docs/formats.md)", role="input")
    p.add_argument("-o", "--output", required=True, metavar="PARAMS.json", help="parameters file to write",
                   role="output", suffixes=(".json",))
    p.add_argument("--method", default=None, kinds=("ocpm_2dof", "planar_2dof"),
                   help="identification method. ocpm_2dof --model paper: hga (default), ga, pso, sa, lm, "
                        "tikhonov, tsvd; --model full: the whole-chain least squares. planar_2dof: tsvd "
                        "(default), ls, gls")
    p.add_argument("--model", default=None, choices=["full", "paper", "simplified", "chain"], kinds=("ocpm_2dof", "planar_2dof"),
                   help="error model. ocpm_2dof: whole closed chain (full, default) or the paper's per-limb "
                        "real IK (paper). planar_2dof: the paper's 4-parameter model (simplified = paper, "
                        "default), all 12 parameters (full), or all 12 on the generic closed-chain core "
                        "(chain: exact model, identifiable base set found, docs/closed_chain.md)")
    p.add_argument("--sigma", type=float, default=None, help="tracker noise, mm (machine default)")
    p.add_argument("--seed", type=int, default=0, help="random seed of stochastic methods (default 0)",
                   kinds=("ocpm_2dof",))
    p.add_argument("--allow-rank-deficient", action="store_true", kinds=("planar_2dof",),
                   help="with --model full: accept a rank-deficient fit (null space reported in the "
                        "file) as success; without it the file says success false and the exit status is 1")
    p.add_argument("--frame", default="base", metavar="base|tracker|tracker:T.json", kinds=("ocpm_2dof",),
                   help="frame of the measured targets: the machine's base frame (default) or the tracker's "
                        "own frame (registration and nest offsets identified; T.json: start registration "
                        "{\"R\": 3x3, \"t_mm\": [x, y, z]}), docs/tracker_frame.md")
    p.add_argument("--nest-tolerance", type=float, default=None, metavar="MM", kinds=("ocpm_2dof",),
                   help="prior of the target nests' offsets from the drawing, mm per coordinate (default 0.5)")
    p.add_argument("--robust", action="store_true", kinds=("ocpm_2dof",),
                   help="robust fit with named outlier rejection also in the base frame (always on with "
                        "--frame tracker or blocked targets)")
    p.add_argument("--history", default=None, metavar="DIR", kinds=("ocpm_2dof", "chain"),
                   help="also file the result into this machine history folder (one JSON per "
                        "calibration, never overwritten; 'pmcal history DIR' compares them), docs/formats.md")
    p.set_defaults(func=_cmd("identify"))

    p = sub.add_parser("compensate", help="corrected motor commands for target orientations")
    p.add_argument("params", metavar="PARAMS.json", help="parameters file written by identify", role="input")
    p.add_argument("--targets", required=False, metavar="TARGETS.csv", role="input",
                   help="targets CSV (phi_deg, theta_deg; planar: x_mm, y_mm); 'pmcal targets' writes one")
    p.add_argument("-o", "--output", required=False, metavar="SETPOINTS.csv", role="output", suffixes=(".csv",),
                   help="setpoints CSV to write: the targets with m1_deg, m2_deg appended")
    p.add_argument("--table", default=None, metavar="TABLE.json", role="output", suffixes=(".json",),
                   companion=(".csv", "pmcal.bridge.comptable_files"), kinds=("ocpm_2dof", "chain"),
                   help="also write the 2-D compensation table (JSON; CSV beside it)")
    p.add_argument("--grid", default=None, metavar="NPHI,NTHETA", kinds=("ocpm_2dof", "chain"),
                   help="table grid: points in phi (0..360 deg) and theta (0..theta_max); default 73,31")
    p.add_argument("--table-version", type=int, default=None, metavar="N", kinds=("ocpm_2dof", "chain"),
                   help="table version (1..2**32-1, must increase on the PLC); default: Unix time")
    p.add_argument("--absolute", action="store_true", kinds=("chain",),
                   help="the table holds absolute motor commands, not corrections to the "
                        "controller's own IK")
    p.add_argument("--force", action="store_true",
                   help="use a calibration that identify flagged not usable (its campaign determines too little)")
    p.set_defaults(func=_cmd("compensate"))

    p = sub.add_parser("evaluate", help="pointing error of a parameter set against a measurement file")
    p.add_argument("params", metavar="PARAMS.json", help="parameters file written by identify", role="input")
    p.add_argument("measurements", metavar="MEAS.csv", help="measurement CSV (docs/formats.md)", role="input")
    p.add_argument("--json", default=None, metavar="OUT.json", help="also write the result as JSON", role="output",
                   suffixes=(".json",))
    p.set_defaults(func=_cmd("evaluate"))

    p = sub.add_parser("diagnose", help="find, name and add the effect the model misses")
    p.add_argument("measurements", metavar="MEAS.csv", help="measurement CSV (docs/formats.md)", role="input")
    p.add_argument("--json", required=True, metavar="OUT.json", help="diagnosis JSON to write (docs/formats.md)",
                   role="output", suffixes=(".json",))
    p.add_argument("--params", default=None, metavar="P.json", role="input", kinds=("ocpm_2dof",),
                   help="start from this parameters file (default: identify from the measurements)")
    p.add_argument("--model", default="full", choices=["full", "paper"], kinds=("ocpm_2dof",),
                   help="baseline model: whole closed chain (full, default) or the paper's (paper)")
    p.add_argument("--report", default=None, metavar="DIR", role="folder", kinds=("ocpm_2dof",),
                   help="also write an HTML report into this folder (replaced as a whole; a folder holding "
                        "files pmcal did not write is refused)")
    p.add_argument("--force", action="store_true", kinds=("ocpm_2dof",),
                   help="accepted for old scripts; changes nothing: a --report folder holding files pmcal did not "
                        "write (an input, yours) is never replaced")
    p.add_argument("--sigma", type=float, default=None, help="tracker noise, mm (else estimated)")
    p.add_argument("--frame", default="base", metavar="base|tracker|tracker:T.json", kinds=("ocpm_2dof",),
                   help="frame of the measured targets (as for identify): tracker: registration, nest offsets "
                        "and outliers identified with the baseline first, docs/tracker_frame.md")
    p.add_argument("--nest-tolerance", type=float, default=None, metavar="MM", kinds=("ocpm_2dof",),
                   help="with --frame tracker: prior of the nests' offsets from the drawing, mm (default 0.5)")
    p.set_defaults(func=_cmd("diagnose"))
