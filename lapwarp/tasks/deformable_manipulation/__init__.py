"""Deformable Manipulation track: TissueManipulation, PickAndPlace, GraspLiftAndTouch (not implemented yet)."""
