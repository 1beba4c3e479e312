"""Digital twin of the planar 2-DOF robot with its measuring mechanism (seed 003).

:mod:`~twin.planar.config` (machine.toml), :mod:`~twin.planar.model` (MJCF with errors),
:mod:`~twin.planar.twin` (loop closure, P and the linear scale), :mod:`~twin.planar.campaign` (noisy
readings), :mod:`~twin.planar.study` (Monte Carlo of the calibration loop), :mod:`~twin.planar.render`.
"""
