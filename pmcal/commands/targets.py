"""``pmcal targets``: write a targets CSV (the input of ``compensate`` and ``twin measure --targets``)."""

from __future__ import annotations

from pmcal.commands.options import CommandSet
from pmcal.commands.routing import dispatch


def register(sub: CommandSet) -> None:
    p = sub.add_parser(
        "targets", help="write a targets CSV: orientations (ocpm_2dof: phi_deg, theta_deg) or positions "
                        "(planar_2dof: x_mm, y_mm) spread over the workspace; format in docs/formats.md")
    p.add_argument("--count", type=int, default=12, metavar="N", help="number of targets (default 12)")
    p.add_argument("--theta-max", type=float, default=None, metavar="DEG", kinds=("ocpm_2dof",),
                   help="largest tilt, deg (default 60, at most 85)")
    p.add_argument("--seed", type=int, default=1, help="random seed of the spread (default 1)")
    p.add_argument("-o", "--output", required=True, metavar="TARGETS.csv", help="the targets CSV to write",
                   role="output", suffixes=(".csv",))
    p.set_defaults(func=lambda a: dispatch("targets", a))
