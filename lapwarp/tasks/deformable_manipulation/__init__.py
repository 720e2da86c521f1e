"""Deformable Manipulation track: TissueManipulation (``tissue_manipulation``), PickAndPlace (``pick_and_place``) and
GraspLiftAndTouch (``grasp_lift_touch``)."""
