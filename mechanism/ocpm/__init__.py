"""The over-constrained 2-DoF rotational parallel mechanism (OCPM, machine ``ocpm_2dof``, Sun et al. 2018):
nominal geometry (:mod:`.config`), error parameters (:mod:`.params`), closed-form kinematics
(:mod:`.kinematics`), measurement sets (:mod:`.data`) and the effect vocabulary (:mod:`.effects`)."""
