"""The over-constrained 2-DoF PM's digital twin (ocpm_2dof's wing of :mod:`pmcal.twin`)."""
