"""Ranges of the options every command shares, checked before any work (issue 33: "check before work").

:func:`check_ranges` reads the parsed namespace once, right after parsing: a value outside its range is
an :class:`pmcal.errors.InputError` naming the option, so a negative seed, a NaN or astronomic noise, or
a port beyond 65535 is answered in one line before anything is built, not by a traceback deep inside
numpy or a silent result of no use. Commands keep their own checks of values whose range depends on the
machine (poses, grids, counts); :func:`parse_task_pose` reads every machine's ``--pose``.
"""

from __future__ import annotations

import math

import numpy as np

from pmcal.errors import InputError
from pmcal.mechanism.machine_spec import NOISE_MAX_MM

#: the largest seed: numpy's legacy generators and MuJoCo's take 32-bit seeds
SEED_MAX = 2**32 - 1
#: a time-out or waiting time, s: a day
SECONDS_MAX = 86400.0

#: namespace attribute -> (option, kind, low, high, low excluded, what it must be); kind int or float (a
#: float must also be finite)
RANGES: dict[str, tuple[str, type, float, float, bool, str]] = {
    "seed": ("--seed", int, 0, SEED_MAX, False, "a random seed must be a whole number"),
    "sigma": ("--sigma", float, 0.0, NOISE_MAX_MM, True, "the tracker noise must be a positive number of mm"),
    "noise": ("--noise", float, 0.0, NOISE_MAX_MM, False, "noise must be a non-negative number of mm"),
    "servo_noise": ("--servo-noise", float, 0.0, 10.0, False, "the servo noise must be a non-negative number of deg"),
    "nest_tolerance": ("--nest-tolerance", float, 0.0, NOISE_MAX_MM, True, "the nests' prior must be a positive number of mm"),
    "timeout": ("--timeout", float, 0.0, SECONDS_MAX, True, "a time-out must be a positive number of seconds"),
    "ack_timeout": ("--ack-timeout", float, 0.0, SECONDS_MAX, True, "a time-out must be a positive number of seconds"),
    "seconds": ("--seconds", float, 0.0, SECONDS_MAX, True, "a duration must be a positive number of seconds"),
    "seconds_per_pose": ("--seconds-per-pose", float, 0.0, SECONDS_MAX, False, "a time must be a non-negative number of seconds"),
    "cycle_ms": ("--cycle-ms", float, 0.0, 1000.0, True, "the PLC cycle must be a positive number of ms"),
    "attempts": ("--attempts", int, 1, 100, False, "attempts must be a whole number"),
    "port": ("--port", int, 0, 65535, False, "a TCP port must be a whole number; 0 picks a free one"),
    "ams_port": ("--ams-port", int, 1, 65535, False, "an AMS port must be a whole number"),
}


def check_ranges(args) -> None:
    """Raise :class:`InputError` for the first option of :data:`RANGES` in ``args`` outside its range."""
    for attr, (option, kind, low, high, low_open, what) in RANGES.items():
        value = getattr(args, attr, None)
        if value is None or isinstance(value, bool) or not isinstance(value, (int, float)):
            continue
        if kind is float and not math.isfinite(value):
            raise InputError(f"{what}, got {value}", field=option)
        below = value <= low if low_open else value < low
        if below or value > high:
            shown = f"{value}" if kind is int else f"{value:g}"
            span = (f"above {low:g} and at most {high:g}" if low_open else
                    f"{int(low)}..{int(high)}" if kind is int else f"{low:g}..{high:g}")
            raise InputError(f"{what} ({span}), got {shown}", field=option)


def parse_task_pose(text: str | None, coordinates: tuple[str, ...]) -> np.ndarray | None:
    """``--pose C1,C2,...`` as task coordinates (mm / deg, the order of machine.toml [task]); None: home."""
    if text is None:
        return None
    try:
        values = np.array([float(v) for v in text.split(",")])
    except ValueError:
        values = np.array([])
    if len(values) != len(coordinates) or not np.isfinite(values).all():
        raise InputError(f"expected {len(coordinates)} comma-separated numbers ({','.join(coordinates)}), "
                         f"got '{text}'", field="--pose")
    return values
