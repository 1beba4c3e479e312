"""Digital twin of the planar 2-DOF robot with its measuring mechanism (paper 003).

:mod:`~pmcal.twin.planar.config` (machine.toml), :mod:`~pmcal.twin.planar.model` (MJCF with errors),
:mod:`~pmcal.twin.planar.twin` (loop closure, P and the linear scale), :mod:`~pmcal.twin.planar.campaign` (noisy
readings), :mod:`~pmcal.apps.planar_study` (Monte Carlo of the calibration loop), :mod:`~pmcal.twin.planar.render`.
"""
