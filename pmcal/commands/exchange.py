"""``pmcal import | export-model | history``: exchange with the tools a calibration engineer already uses.

``import`` joins a tracker export and a controller log into the measurement CSV; ``export-model`` writes
the calibrated MuJoCo model (MJCF); ``history`` tables and plots a machine's calibrations over time.
Formats: docs/formats.md ("Tracker exports and controller logs", "Calibration history").
"""

from __future__ import annotations

from pmcal.commands.options import CommandSet
from pmcal.errors import InputError


def _import(args) -> int:
    from pmcal.commands.routing import dispatch

    return dispatch("import_campaign", args)


def _export_model(args) -> int:
    from pmcal.commands.routing import dispatch

    return dispatch("export_model", args)


def _history(args) -> int:
    from pmcal.history import compare, estimates, history_table, read_history, unit_of

    if not 0 < args.alpha < 1:
        raise InputError(f"alpha must be in (0, 1), got {args.alpha}", field="--alpha")
    records = read_history(args.folder)
    changes = compare(records[-2], records[-1], args.alpha) if len(records) > 1 else None
    header, rows = history_table(records, changes)
    print(f"{len(records)} calibration(s) of {records[-1].machine} in {args.folder}, last "
          f"{records[-1].date:%Y-%m-%d %H:%M} UTC" + ("" if changes is None else
                                                     f", previous {records[-2].date:%Y-%m-%d %H:%M} UTC"))
    fmt = lambda v, sign: v if isinstance(v, str) else ("–" if v != v else f"{v:{sign}.4f}")  # noqa: E731
    table = [header] + [[fmt(c, "" if header[i].startswith("+-") else "+") for i, c in enumerate(row)] for row in rows]
    widths = [max(len(r[i]) for r in table) for i in range(len(header))]
    for row in table:
        print("  ".join(c.ljust(w) if i < 2 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths))))
    moved = [c for c in changes or [] if c.flagged]
    if changes is not None:
        print("moved: " + (", ".join(f"{c.name} {c.estimate:+.4g} {unit_of(c.name, records[-1])}"
                                     for c in moved) if moved else "nothing") + f" (family-wise alpha {args.alpha:g})")
        for c in moved:                           # a machine folder's base parameter: what it stands for
            if estimates(records[-1], c.name):
                print(f"  {c.name} estimates {estimates(records[-1], c.name)}")
    if args.report:
        from pmcal.reports.history import history_report

        history_report(records, changes, str(args.folder), args.alpha).write(args.report)
    return 0


def register(sub: CommandSet) -> None:
    p = sub.add_parser("import", help="join a tracker export and a controller log into a measurement CSV")
    p.add_argument("tracker", metavar="TRACKER.txt", role="input",
                   help="tracker export: Spatial Analyzer's ASCII point export (names, x y z, optional tolerance, "
                        "uncertainty and time stamp; space or comma separated; '//' comments), or a CSV with "
                        "--columns; docs/formats.md")
    p.add_argument("--log", required=True, metavar="LOG.csv", role="input",
                   help="controller log CSV: pose_id, the machine's motor columns as in its measurement file "
                        "(m1_cmd_deg, m2_cmd_deg ..., _mm for a prismatic motor), optional time_s (s), temp_c "
                        "(degC)")
    p.add_argument("-o", "--output", required=True, metavar="MEAS.csv", role="output", suffixes=(".csv",),
                   help="measurement CSV to write (docs/formats.md); frame and units in its '#' header")
    p.add_argument("--units", default=None, choices=["mm", "in"],
                   help="length unit of the export: mm or in (inches); default the export header's, else mm")
    p.add_argument("--names", default=None, metavar="REGEX",
                   help="pattern of the point names (name fields joined by one space) with named groups "
                        "'pose' (its digits are the log's pose number: P007 is pose 7) and 'target' (the nest: "
                        "T1, T2, ... or its site name in machine.toml); default: last field target, the one before it pose, a collection ignored")
    p.add_argument("--columns", default=None, metavar="name=COL,x=COL,y=COL,z=COL[,time=COL]",
                   help="read a plain CSV of points instead, with this column map (pose=COL,target=COL instead "
                        "of name=COL allowed); coordinates in --units")
    p.add_argument("--time-tolerance", type=float, default=None, metavar="S",
                   help="join points without a pose in their name to the log row nearest in time within this "
                        "many seconds (time stamps on both sides, same clock)")
    p.set_defaults(func=_import)

    p = sub.add_parser("export-model", help="write the calibrated machine as a MuJoCo model (MJCF)")
    p.add_argument("params", metavar="PARAMS.json", role="input",
                   help="parameters file of identify (or params.json of 'diagnose --report DIR': adds the named "
                        "effects); docs/formats.md")
    p.add_argument("-o", "--output", required=True, metavar="CALIBRATED.xml", role="output", suffixes=(".xml",),
                   companion=(".toml", "pmcal.export_model"),
                   help="MJCF file to write (self-contained, SI units); a machine.toml with the calibration and "
                        "the effects MJCF cannot hold is written beside it with the suffix .toml")
    p.set_defaults(func=_export_model)

    p = sub.add_parser("history", help="a machine's calibrations over time: what moved since the last one")
    p.add_argument("folder", metavar="DIR", help="history folder that 'pmcal identify ... --history DIR' files into")
    p.add_argument("--report", default=None, metavar="HISTORY.html", role="output", suffixes=(".html",),
                   help="also write an HTML report (every parameter over time with its 95 %% band)")
    p.add_argument("--alpha", type=float, default=0.05, metavar="P",
                   help="family-wise false-flag rate of the test between the last two calibrations (default 0.05)")
    p.set_defaults(func=_history)
