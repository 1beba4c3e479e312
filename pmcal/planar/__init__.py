"""planar_2dof's library: its calibration and file formats (its wing of the application)."""
