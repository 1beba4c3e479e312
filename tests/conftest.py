"""Shared test set-up: headless rendering, and the repository root on sys.path for `benchmarks`."""

import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def run_quietly_in(folder: Path, *argvs: list[str]) -> Path:
    """Run ``pmcal`` command lines in ``folder`` (``--quiet``; each must succeed); returns ``folder``."""
    from pmcal.cli import main

    cwd = os.getcwd()
    os.chdir(folder)
    try:
        for argv in argvs:
            assert main(list(argv) + ["--quiet"]) == 0, argv
    finally:
        os.chdir(cwd)
    return folder
