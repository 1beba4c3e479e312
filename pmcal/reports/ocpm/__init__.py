"""ocpm_2dof's reports (demo, diagnosis)."""
