"""Per-machine application modules (see :mod:`pmcal.machines`), and what their commands share: the error
statistics of ``evaluate``, the export of a calibrated model (``export-model``), the import of a tracker
campaign (``import``)."""

import numpy as np


def error_stats(values) -> dict[str, float]:
    """``rms``, ``mean`` (of the magnitudes) and ``max`` magnitude of an array of errors, NaN ignored (a
    blocked target, a pose left out)."""
    a = np.asarray(values, float)
    return {"rms": float(np.sqrt(np.nanmean(a**2))), "mean": float(np.nanmean(np.abs(a))),
            "max": float(np.nanmax(np.abs(a)))}


def export_calibrated_model(parts, args, machine_name: str, keep=None) -> int:
    """``export-model PARAMS.json -o MODEL.xml``: write the calibrated MJCF and its machine.toml from a
    machine's :class:`pmcal.export_model.ExportParts`, say where each named effect went. ``keep``: a folder
    never written into (default the selected machine's)."""
    from pmcal import progress
    from pmcal.export_model import export_model

    if keep is None and getattr(args, "selected_machine", None) is not None:
        keep = args.selected_machine.folder            # the machine's own folder is never written into
    out = export_model(parts, args.params, args.output, keep=keep)
    for name, where in out["in_mjcf"].items():
        progress.status(f"{name}: in the MJCF ({where})")
    for name in out["comment_only"] + out["not_in_mjcf"]:
        progress.warning(f"{name} cannot be held by MJCF: written to {out['toml']} (and the file's comment)")
    held = len(out["comment_only"]) + len(out["not_in_mjcf"])
    print(f"calibrated model of {machine_name} from {args.params}: {len(out['in_mjcf'])} effect(s) in the MJCF"
          + (f", {held} only in {out['toml']}" if held else ""))
    return 0


def import_tracker_campaign(args, join, write, advice: str) -> int:
    """``pmcal import TRACKER LOG -o MEAS.csv``: read the tracker export (Spatial Analyzer ASCII, or a CSV of
    named points with ``--columns``), ``join(export) -> ImportResult`` it with the controller log the
    machine's way, say what could not be placed and whether the points are in the base frame (else
    ``advice``), then ``write(result)`` the measurement CSV (:mod:`pmcal.io_tracker`)."""
    import numpy as np

    from pmcal import progress
    from pmcal.errors import InputError
    from pmcal.io_tracker import parse_columns, read_point_csv, read_sa_ascii

    if args.time_tolerance is not None and not args.time_tolerance > 0:
        raise InputError(f"time tolerance must be a positive number of seconds, got {args.time_tolerance}",
                         field="--time-tolerance")
    if args.columns:
        export = read_point_csv(args.tracker, parse_columns(args.columns), args.units)
    else:
        export = read_sa_ascii(args.tracker, args.units)
    with np.errstate(over="ignore", invalid="ignore"):   # 1e300 mm: refused by the join's checks, not a warning
        res = join(export)
    for w in res.warnings:
        progress.warning(w)
    if res.frame != "base":
        progress.warning(f"{args.tracker}: the points are not in the machine's base frame ({res.frame_reason}): "
                         f"{advice}")
    write(res)
    print(f"imported {len(res.meas)} poses ({res.join}, {res.frame} frame)")
    return 0
