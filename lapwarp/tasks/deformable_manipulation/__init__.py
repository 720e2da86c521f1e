"""Deformable Manipulation track: TissueManipulation (``tissue_manipulation``); PickAndPlace and GraspLiftAndTouch
are not implemented yet."""
