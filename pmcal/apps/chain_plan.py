"""``pmcal --machine DIR twin plan``: the poses to measure, chosen D-optimally for identification (routed
from :mod:`pmcal.apps.chain`; the method: :mod:`pmcal.calib.chain_design`). The plan CSV holds the commands
to drive in order (docs/formats.md, "Any machine"); ``twin measure --plan`` measures it on the twin.
"""

from __future__ import annotations

import numpy as np

from pmcal import progress
from pmcal.chain import plan
from pmcal.errors import InputError
from pmcal.io_chain import write_plan

#: fewest and most poses of a plan
PLAN_POSES = (1, 1000)


def twin_plan(args) -> int:
    """Write the plan; print how much better it determines the errors than as many random poses."""
    machine = args.selected_machine
    lo, hi = PLAN_POSES
    if not lo <= args.poses <= hi:
        raise InputError(f"poses must be {lo}..{hi}, got {args.poses}", field="--poses")
    progress.status(f"planning {args.poses} poses of {machine.name}")
    try:
        design = plan(machine, args.poses, args.seed)
    except ValueError as exc:                # fewer coordinates than base errors
        raise InputError(str(exc), field="--poses") from None
    ratio = design.std_random / design.std
    write_plan(args.output, machine.spec, design.commands, [
        f"pmcal twin plan: machine {machine.name}, {args.poses} poses chosen D-optimally from {design.pool} drawn "
        f"over the workspace (seed {args.seed}), in driving order from the home keyframe",
        f"determines {design.determined} base errors; their uncertainty is {design.gain:.2f}x smaller (geometric "
        f"mean; {ratio.min():.2f}x .. {ratio.max():.2f}x) than with {args.poses} random poses",
        "drive the rows in this order; log the tracker targets t1_x .. at each (the measurement CSV)"])
    print(f"{args.poses} poses determine {design.determined} base errors, with uncertainties {design.gain:.2f}x "
          f"smaller (geometric mean) than {args.poses} random poses give")
    return 0

