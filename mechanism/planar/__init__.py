"""The planar 2-DOF parallel robot with its measuring mechanism (machine ``planar_2dof``, Mei et al. 2017):
geometry and parameters (:mod:`.geometry`), kinematics (:mod:`.kinematics`), sensor noise (:mod:`.noise`)."""
