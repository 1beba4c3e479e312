"""An independent simulator of the over-constrained 2-DoF PM, written from the machine description (docs/ocpm_2dof.md, the paper) with plain
numpy/scipy and sharing no code with pmcal: the project's guard against fitting its own generator.

`machine` (geometry, closed-chain solve, effects), `campaign` (campaigns and the measurement CSV).
See tests/crosssim/README.md.
"""
