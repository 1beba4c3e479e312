"""Machine description: geometry, parameters, kinematics, measurement and effect types of each machine.

The lowest layer of pmcal (numpy only, plus the machine configuration files in :mod:`pmcal.mjcf`):
everything else (twin, identification, bridge, application) builds on it, and it imports none of them.

- :mod:`~pmcal.mechanism.ocpm` — the over-constrained 2-DoF rotational parallel mechanism (OCPM) of
  Sun et al. 2018: an SS limb and four RSR limbs (machine name ``ocpm_2dof``).
- :mod:`~pmcal.mechanism.planar` — the planar 2-DOF parallel robot with its measuring mechanism of
  Mei et al. 2017 (machine name ``planar_2dof``).
- :mod:`~pmcal.mechanism.machine_spec` — a closed-chain machine as data: ``machine.toml`` beside an MJCF,
  validated at load (:mod:`~pmcal.mechanism.mjcf_names` reads the MJCF's names without MuJoCo);
  :mod:`~pmcal.mechanism.task_space` — its task coordinates.
- :mod:`~pmcal.mechanism.rotations`, :mod:`~pmcal.mechanism.rigid` — rotations and rigid fits.

Units inside: mm and radians unless a name says otherwise (``*_deg``).
"""
