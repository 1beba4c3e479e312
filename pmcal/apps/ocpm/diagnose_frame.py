"""The measurement frame of ``pmcal diagnose`` (docs/tracker_frame.md): tracker-frame data registered with
the diagnosis baseline first, blocked targets left out and named. Units mm and degrees.
"""

from __future__ import annotations

import numpy as np

from pmcal import progress
from pmcal.errors import InputError
from pmcal.ocpm.io import LONG_POSES, read_measurements
from pmcal.calib.ocpm.diagnose import BASELINES
from pmcal.mechanism.ocpm.config import Geometry


def frame_input(args, geom: Geometry, sigma: float | None, min_poses: int):
    """The measurements as the diagnosis takes them, in the base frame with complete rows, the frame part
    of the JSON and notes (docs/tracker_frame.md). ``--frame tracker``: registered first with the
    diagnosis baseline (:func:`pmcal.ocpm.tracker_frame.register_for_diagnosis`; the baseline then keeps a
    small base-frame correction, :func:`pmcal.ocpm.tracker_frame.with_frame_correction`). A row with a blocked
    target is left out and named, in either frame."""
    from pmcal.ocpm.tracker_frame import check_nest_tolerance, parse_frame, register_for_diagnosis, warn_rejected

    frame, reg0 = parse_frame(getattr(args, "frame", None))
    nest_std = check_nest_tolerance(getattr(args, "nest_tolerance", None))
    meas = read_measurements(args.measurements, geom, frame=frame)
    progress.set_long(len(meas) > LONG_POSES)
    if frame == "tracker":
        from pmcal.twin.ocpm.forward import FullChainModel

        if len(meas) < min_poses:
            raise InputError(f"{len(meas)} poses are too few to tell an effect from the geometry: measure at "
                             f"least {min_poses} (the diagnosis campaign has 128)", file=args.measurements,
                             field="pose_id")
        progress.status(f"registering the tracker frame with the baseline ({len(meas)} poses)")
        model = args.model or "full"
        meas, doc, notes = register_for_diagnosis(meas, FullChainModel(geom), sigma or geom.sigma_mm,
                                                  BASELINES[model], model == "full", reg0,
                                                  nest_std, str(args.measurements))
        warn_rejected(doc)
        for r in doc.get("registration_left_out", []):
            progress.warning(f"row {r['row']} ({r['pose_id']}) left out of the registration: {r['why']}")
        for r in doc.get("rows_left_out", []):
            if "cannot assemble" in r["why"]:
                progress.warning(f"row {r['row']} ({r['pose_id']}) left out: {r['why']}")
        return meas, doc, notes
    blocked = np.flatnonzero(~meas.visible.all(axis=1))
    if not blocked.size:
        return meas, {}, []
    keep = np.flatnonzero(meas.visible.all(axis=1))
    note = (f"{blocked.size} row(s) left out (blocked target; the diagnosis takes complete rows): rows "
            + ", ".join(str(i + 1) for i in blocked))
    doc = {"frame": "base", "rows_left_out": [{"row": int(i) + 1, "pose_id": meas.pose_id[i],
                                               "why": "blocked target"} for i in blocked]}
    if meas.approach is None:                         # the order is the whole campaign's
        from dataclasses import replace

        from pmcal.mechanism.ocpm.effects import approach_from_order

        meas = replace(meas, approach=approach_from_order(meas.m_cmd_deg))
        keep = keep[keep > 0]
        note += "; approach inferred from the whole campaign's row order first (row 1 left out, unknown)"
    return meas.subset(keep), doc, [note]
