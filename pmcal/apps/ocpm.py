"""Application of the over-constrained 2-DoF PM (``--machine ocpm_2dof``, the default).

Each command lives in the module that owns its subject; this module only routes (lazily, so a command
imports only what it needs).
"""

from __future__ import annotations


def twin_measure(args) -> int:
    from pmcal.apps.ocpm_twin import twin_measure as run
    return run(args)


def twin_render(args) -> int:
    from pmcal.apps.ocpm_twin import twin_render as run
    return run(args)


def identify(args) -> int:
    from pmcal.apps.ocpm_calib import identify as run
    return run(args)


def compensate(args) -> int:
    from pmcal.apps.ocpm_calib import compensate as run
    return run(args)


def evaluate(args) -> int:
    from pmcal.apps.ocpm_calib import evaluate as run
    return run(args)


def demo(args) -> int:
    from pmcal.apps.ocpm_calib import demo as run
    return run(args)


def diagnose(args) -> int:
    from pmcal.apps.ocpm_diagnose import diagnose as run
    return run(args)
