"""ocpm_2dof's demo studies."""
