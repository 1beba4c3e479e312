"""The over-constrained 2-DoF rotational PM of paper 000 (Sun et al. 2018): SS limb + four RSR limbs."""
