"""``pmcal twin measure|plan|render``: virtual measurement campaigns and pictures of the digital twin."""

from __future__ import annotations

from pmcal.commands.options import Command, CommandSet
from pmcal.errors import InputError
from pmcal.commands.routing import dispatch

#: image size limits of ``twin render`` (pixels): the offscreen buffer of the MJCF models
IMAGE_LIMITS = {"width": 1280, "height": 960}


def _render(args) -> int:
    for name, most in IMAGE_LIMITS.items():
        value = getattr(args, name)
        if not 16 <= value <= most:
            raise InputError(f"image {name} must be 16..{most} pixels, got {value}", field=f"--{name}")
    return dispatch("twin_render", args)


def register(sub: CommandSet) -> None:
    p = sub.add_parser("twin", help="the digital twin: virtual measurement campaigns, pictures")
    tsub = p.add_subparsers(dest="twin_command", metavar="TWIN_COMMAND", required=True)

    m = tsub.add_parser("measure", help="measure a virtual campaign on the twin and write the CSV")
    _machine_errors(m)
    m.add_argument("--poses", type=int, default=None, metavar="N",
                   help="number of poses (default: ocpm_2dof 24; planar_2dof 6, the paper's, even and >= 6)")
    m.add_argument("--targets", default=None, metavar="TARGETS.csv", role="input",
                   help="explicit target orientations (phi_deg, theta_deg) instead of planned poses")
    m.add_argument("--plan", role="input", default=None, metavar="PLAN.csv", kinds=("chain",),
                   help="the commands of a campaign plan ('twin plan') instead of drawn poses")
    m.add_argument("--noise", type=float, default=None, metavar="MM",
                   help="tracker noise, standard deviation per coordinate, mm (default from the machine)")
    m.add_argument("--servo-noise", type=float, default=None, metavar="DEG", kinds=("planar_2dof",),
                   help="servo noise, standard deviation per motor, deg (default eq. 35)")
    m.add_argument("--seed", type=int, default=1, help="random seed (poses, approach, noise)")
    m.add_argument("--theta-max", type=float, default=None, metavar="DEG", kinds=("ocpm_2dof",),
                   help="largest tilt of planned poses, deg (default from the machine, 60)")
    m.add_argument("--no-random-approach", action="store_true", kinds=("ocpm_2dof",),
                   help="approach every pose from the same side (default: random per motor)")
    m.add_argument("--effect", action="append", default=[], metavar="NAME=VALUE", kinds=("ocpm_2dof",),
                   help="switch on a physical effect (repeatable; NAME=V1,V2 per motor), see docs/effects.md")
    m.add_argument("--payload", default=None, metavar="KG[,KG...]", kinds=("ocpm_2dof",),
                   help="payload levels on the platform, kg, spread over the poses (e.g. 0,10)")
    m.add_argument("--temperature", default=None, metavar="DEGC[,DEGC]", kinds=("ocpm_2dof",),
                   help="machine temperature: constant, or a ramp from the first to the second value")
    m.add_argument("--shuffle", action="store_true", kinds=("ocpm_2dof",),
                   help="measure the planned poses in random order (default: in order of tilt)")
    m.add_argument("--seconds-per-pose", type=float, default=30.0, metavar="S", kinds=("ocpm_2dof", "chain"),
                   help="time between poses, s (time_s column; default 30)")
    m.add_argument("--tracker-pose", default=None, metavar="X,Y,Z,RX,RY,RZ|random", kinds=("ocpm_2dof",),
                   help="measure in the tracker's own frame: pose of the base frame in the tracker frame "
                        "(mm; rotation vector, deg), or 'random' (1-3 m away, any yaw, +-2 deg tilt; from "
                        "--seed); default: the base frame (docs/tracker_frame.md)")
    m.add_argument("--nest-error", type=float, default=0.0, metavar="MM", kinds=("ocpm_2dof",),
                   help="target nests off the drawing by this much (1 sigma per coordinate, shape part), mm")
    m.add_argument("--blocked", type=float, default=0.0, metavar="P", kinds=("ocpm_2dof",),
                   help="probability that a row has one target blocked (its three cells left empty)")
    m.add_argument("--outliers", default=None, metavar="N[:MM]", kinds=("ocpm_2dof",),
                   help="N rows with a gross error in one coordinate of one target (default 2 mm)")
    m.add_argument("-o", "--output", required=True, metavar="MEAS.csv", role="output", suffixes=(".csv",),
                   help="measurement CSV to write (columns: docs/formats.md)")
    m.set_defaults(func=lambda a: dispatch("twin_measure", a))

    pl = tsub.add_parser("plan", help="write the command list of a campaign (poses in measurement order)")
    pl.add_argument("--for-diagnosis", action="store_true", kinds=("ocpm_2dof",),
                    help="the campaign pmcal diagnose needs (random order, payloads, warm-up/cool-down)")
    pl.add_argument("--frame", choices=["base", "tracker"], default="base", kinds=("ocpm_2dof",),
                    help="tracker: the campaign a tracker-frame calibration should measure (D-optimal for the "
                         "machine, registration and nests; 48 poses to 80 deg recommended), docs/tracker_frame.md")
    pl.add_argument("--poses", type=int, default=128, help="number of poses (default 128)")
    pl.add_argument("--theta-max", type=float, default=80.0, metavar="DEG", help="largest tilt, deg (default 80)",
                    kinds=("ocpm_2dof",))
    pl.add_argument("--seed", type=int, default=1, help="random seed of the poses and their order")
    pl.add_argument("--from", dest="from_diagnosis", default=None, metavar="DIAG.json", role="input", kinds=("ocpm_2dof",),
                    help="a diagnosis JSON: list what it could not identify and how to fix it")
    pl.add_argument("-o", "--output", required=True, metavar="PLAN.csv", role="output", suffixes=(".csv",),
                    help="the campaign's command list to write (CSV: pose_id, m1_cmd_deg, m2_cmd_deg, ...)")
    pl.set_defaults(func=lambda a: dispatch("twin_plan", a))

    r = tsub.add_parser("render", help="write a PNG of the machine at a pose")
    _machine_errors(r)
    r.add_argument("--pose", default="0,0", metavar="PHI,THETA", help="orientation in deg (default 0,0)")
    r.add_argument("--width", type=int, default=800, metavar="PX", help="image width, pixels, 16..1280 (default 800)")
    r.add_argument("--height", type=int, default=600, metavar="PX",
                   help="image height, pixels, 16..960 (default 600)")
    r.add_argument("-o", "--output", required=True, metavar="IMAGE.png", help="PNG file to write", role="output",
                   suffixes=(".png",))
    r.set_defaults(func=_render)


def _machine_errors(p: Command) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--preset", default=None, metavar="NAME", kinds=("ocpm_2dof", "planar_2dof"),
                   help="built-in error set: ocpm_2dof nominal (default) or paper-table2; planar_2dof nominal "
                        "or group1..group6 (the paper's error groups)")
    g.add_argument("--errors", default=None, metavar="PARAMS.json", role="input",
                   help="error set of the real machine: a parameters file (docs/formats.md)")
    p.add_argument("--stiffness-ratio", type=float, default=None, metavar="RATIO", kinds=("ocpm_2dof",),
                   help="actuated-closure/SS over passive-closure stiffness, > 0 (default "
                        "from the machine)")
