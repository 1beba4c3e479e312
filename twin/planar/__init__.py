"""The planar robot (paper 003) on the generic closed-chain core.

:mod:`~pmcal.twin.planar.config` (the paper's machine.toml: geometry, noise, presets, calibration and design
settings), :mod:`~pmcal.twin.planar.twin` (the twin: ``mjcf/planar_2dof/chain`` on
:class:`pmcal.twin.closed_chain.ClosedChainTwin`, the paper's campaigns, pictures).
"""
