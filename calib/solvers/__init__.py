"""Identification methods behind one call signature, returning :class:`IdentResult`."""

from calib.solvers.result import IdentResult

__all__ = ["IdentResult"]
