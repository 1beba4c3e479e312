"""Per-machine application modules (see :mod:`pmcal.machines`)."""
