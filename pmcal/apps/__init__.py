"""Per-machine application modules (see :mod:`pmcal.machines`), and what their commands share: the error
statistics of ``evaluate``, the export of a calibrated model (``export-model``)."""

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
