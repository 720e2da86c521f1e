"""Spatial Reasoning track: Reach, DeflectSpheres, SearchForPoint."""
