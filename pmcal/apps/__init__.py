"""Per-machine application modules (see :mod:`pmcal.machines`), and what their ``evaluate`` commands share."""

import numpy as np


def error_stats(values) -> dict[str, float]:
    """``rms``, ``mean`` (of the magnitudes) and ``max`` magnitude of an array of errors, NaN ignored (a
    blocked target, a pose left out)."""
    a = np.asarray(values, float)
    return {"rms": float(np.sqrt(np.nanmean(a**2))), "mean": float(np.nanmean(np.abs(a))),
            "max": float(np.nanmax(np.abs(a)))}
