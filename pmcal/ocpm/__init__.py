"""ocpm_2dof's library: its calibration, compensation, file formats and tracker-frame fit (its wing of the application)."""
