"""``pmcal --machine DIR demo``: plan, measure, identify, compensate and build the table in one go on a
machine folder's twin (routed from :mod:`pmcal.apps.chain`; the study: :mod:`pmcal.studies.chain_demo`)."""

from __future__ import annotations

from pathlib import Path

from pmcal.studies.chain_demo import run_chain_demo


def demo(args) -> int:
    """``pmcal --machine DIR demo``: :func:`pmcal.studies.chain_demo.run_chain_demo` into ``--out``."""
    return run_chain_demo(args.selected_machine, Path(args.out), args.seed)
