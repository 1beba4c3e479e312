"""Identification, diagnosis and compensation numerics (numpy/scipy; no MuJoCo, no CLI).

No user files: calib reads and writes none of the user's files (those are :mod:`pmcal.ocpm.io`,
:mod:`pmcal.planar.io`); it does read package data through :mod:`pmcal.mechanism` (the machine
configuration ``mjcf/<machine>/machine.toml``: default tracker noise, stiffness ratio), and the diagnosis
inspects installed shared libraries to pin BLAS threads.

The algorithms reach the physics only through :class:`pmcal.calib.ocpm.forward_model.ForwardModel` objects
handed to them (the twin's, or any other simulator's); the machine description comes from
:mod:`pmcal.mechanism`. Units inside: mm and radians unless a name says otherwise (``*_deg``);
interfaces to files and users are in degrees and converted at the edge.

- :mod:`~pmcal.calib.solvers` — identification methods behind one signature and one result type.
- :mod:`~pmcal.calib.identifiability`, :mod:`~pmcal.calib.pose_selection` — what a campaign determines.
- :mod:`~pmcal.calib.ocpm` — the over-constrained PM: the paper's per-limb model and procedure, the whole
  closed chain, the discrepancy diagnosis, compensation.
- :mod:`~pmcal.calib.planar` — the planar robot: identification on adjacent positions, TSVD, design.
- :mod:`~pmcal.calib.closed_chain` — any closed-chain machine described as data, through the protocol
  :class:`pmcal.calib.chain_model.ChainModel`: base-parameter reduction, identification, CRLB, compensation.
"""
