"""Writers of tracker exports and controller logs as the real tools lay them out (for tests and benchmarks).

Written separately from :mod:`pmcal.io_tracker` (the reader under test): Spatial Analyzer's ASCII point
export as its manual describes it (``//`` SA version and frame comments, ``Collection Group Target`` names,
optional tolerance / uncertainty / time-stamp fields, space or comma separators), and a controller log CSV.
"""

from datetime import datetime, timedelta, timezone


START = datetime(2026, 11, 25, 8, 0, 0, tzinfo=timezone.utc)


def write_sa_export(path, meas, units="in", frame="OCPM::Base", blocked=(), reshoot=(), separator=" ",
                    collection="OCPM", stamps=True, names="Collection Group Target", decimals=6, targets=None):
    """The points of ``meas`` (mm) as an SA ASCII export in ``units`` (``mm`` or ``in``).

    ``blocked``: (row, nest) pairs left out; ``reshoot``: (row, nest) pairs written twice, first with a
    2 mm error in x (the shot the operator repeated); ``targets``: the nests' point names (default T1, T2..)."""
    scale = {"mm": 1.0, "in": 1 / 25.4}[units]
    unit_word = {"mm": "Millimeters", "in": "Inches"}[units]
    lines = ["// SpatialAnalyzer Version 2023.1.0601.7", f"// Frame: {frame}",
             "// Axis: Cartesian (X, Y, Z)", f"// Units: {unit_word}"]
    for i, pid in enumerate(meas.pose_id):
        group = f"P{int(''.join(c for c in pid if c.isdigit())):03d}"
        t0 = START + timedelta(seconds=float(meas.time_s[i]) if meas.time_s is not None else 30.0 * i)
        for n in range(meas.targets.shape[1]):
            if (i, n) in blocked:
                continue
            xyz = meas.targets[i, n] * scale
            target = targets[n] if targets else f"T{n + 1}"
            name = {"Collection Group Target": [collection, group, target],
                    "Group Target": [group, target], "Target": [target]}[names]
            when = t0 + timedelta(seconds=3 * n)
            shots = [xyz + [2.0 * scale, 0, 0], xyz] if (i, n) in reshoot else [xyz]
            for k, v in enumerate(shots):
                fields = name + [f"{c:.{decimals}f}" for c in v] + ["0.0020", "0.0004"]
                if stamps:
                    fields.append((when + timedelta(seconds=20 * k)).strftime("%m/%d/%Y %I:%M:%S %p"))
                sep = separator if (i + n) % 4 else ", "      # mixed separators, as hand-merged files have
                lines.append(sep.join(fields))
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("\n".join(lines) + "\n")


def write_log(path, meas, numbers=True, posix_time=False, motor_columns=("m1_cmd_deg", "m2_cmd_deg")):
    """The controller's log: pose_id (the number only, as controllers write it), commands (``meas.commands``
    or ``meas.m_cmd_deg``, under ``motor_columns``), time, temp."""
    commands = meas.commands if hasattr(meas, "commands") else meas.m_cmd_deg
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("# controller log of the campaign\n")
        cols = ["pose_id", *motor_columns, "time_s"] + (["temp_c"] if meas.temp_c is not None else [])
        fh.write(",".join(cols) + "\n")
        for i, pid in enumerate(meas.pose_id):
            label = str(int("".join(c for c in pid if c.isdigit()))) if numbers else pid
            t = float(meas.time_s[i]) if meas.time_s is not None else 30.0 * i
            if posix_time:
                t += START.timestamp()
            row = [label, *(f"{v:.6f}" for v in commands[i]), f"{t:.3f}"]
            if meas.temp_c is not None:
                row.append(f"{meas.temp_c[i]:.2f}")
            fh.write(",".join(row) + "\n")
