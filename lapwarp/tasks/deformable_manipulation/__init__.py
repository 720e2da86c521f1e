"""Deformable Manipulation track: TissueManipulation (``tissue_manipulation``) and PickAndPlace (``pick_and_place``);
GraspLiftAndTouch is not implemented yet."""
