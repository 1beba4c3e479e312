"""The planar 2-DOF translational robot with its distance-measuring mechanism (paper 003, Mei et al. 2017).

Modules, one job each (mm and radians throughout; seed frame O-xy, x horizontal, y up, the platform hangs
below the base at y < 0; see ``docs/planar.md``):

- :mod:`~pmcal.mechanism.planar.geometry` — nominal geometry, source errors, parameter names and units.
- :mod:`~pmcal.mechanism.planar.kinematics` — closed-form inverse/forward kinematics (eq. 1-8), error transfer
  matrices (eq. 9-13), the measuring-mechanism vector (eq. 4, 14).
- :mod:`~pmcal.calib.planar.identification` — identification model on adjacent positions (eq. 14-28), TSVD
  (eq. 27, 29), the full least-squares model (eq. 25), reading covariance (eq. 34-35).
- :mod:`~pmcal.calib.planar.design` — measurement positions (Fig. 7), condition numbers (eq. 31, Fig. 8),
  noise-optimal positions.
- :mod:`~pmcal.calib.planar.calibration` — repeated identification with the MAEMM correction (eq. 30) and the
  iterative compensation (eq. 32-33).
- :mod:`~pmcal.mechanism.planar.noise` — scale and servo noise of the paper's simulation (eq. 34-35).
"""
