"""``pmcal --machine DIR diagnose MEAS.csv --json OUT.json``: what a machine folder's geometric model leaves in
a campaign, named only when a family explains it on held-out rows (:mod:`pmcal.calib.chain_diagnose`;
routed from :mod:`pmcal.apps.chain`). Units: mm; values in each family's unit."""

from __future__ import annotations

from pmcal import progress
from pmcal.calib.chain_diagnose import diagnose_chain
from pmcal.chain import identify
from pmcal.errors import InputError
from pmcal.fileio import write_json
from pmcal.io_chain import read_measurements


def diagnosis_document(machine, dg, source: str) -> dict:
    """The diagnosis JSON of a machine folder (docs/formats.md, "Any machine")."""
    return {
        "mechanism": machine.name, "measurements": source, "verdict": dg.verdict,
        "effects": [e.name for e in dg.named], "unit": "mm", "noise_floor": dg.noise_mm,
        "gap_before": dg.gap_before, "gap_after": dg.gap_after, "time_unit": dg.time_unit,
        "named": [{"name": e.name, "motors": e.motors, "held_out_share": e.held_out_share, "p_value": e.p_value,
                   "fix": e.fix,
                   "values": {lab: {"value": float(v), "std": float(s), "interval": [float(a), float(b)], "unit": u}
                              for lab, v, s, (a, b), u in zip(e.labels, e.values, e.std, e.interval, e.units)}}
                  for e in dg.named],
        "candidates": [{k: (float(v) if isinstance(v, float) else v) for k, v in c.items()} for c in dg.candidates],
        "unexplained": dg.unexplained,
        "significant_unnamed": [{"name": c["name"], "p_value": float(c["p_value"]), "verdict": c["verdict"]}
                                for c in dg.found_unnamed],
    }


def diagnose(args) -> int:
    machine = args.selected_machine
    if args.sigma is not None and not args.sigma > 0:
        raise InputError(f"tracker noise must be a positive number of mm, got {args.sigma}", field="--sigma")
    meas = read_measurements(args.measurements, machine.spec)
    progress.status(f"identifying, then testing what the geometry leaves in {len(meas)} poses")
    res = identify(machine, meas, args.sigma)
    dg = diagnose_chain(machine.twin, meas.commands, meas.targets, res, time_s=meas.time_s, temp_c=meas.temp_c,
                        motor_units=[m.unit for m in machine.spec.motors])
    print(dg.summary())
    for e in dg.named:
        print(f"  {e.name}: {e.fix}")
    write_json(args.json, diagnosis_document(machine, dg, str(args.measurements)))
    return 0
