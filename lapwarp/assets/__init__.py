"""Procedural assets: tet grids, hollow cylinders, voxelised organs, cloth grids, rod polylines and loops."""

from lapwarp.assets.meshes import (
    box_tets,
    cloth_grid,
    ellipsoid_tets,
    hollow_cylinder_tets,
    rod_circle,
    rod_polyline,
    ruled_sheet_tets,
    tet_surface,
    voxel_tets,
)

__all__ = ["box_tets", "cloth_grid", "ellipsoid_tets", "hollow_cylinder_tets", "rod_circle", "rod_polyline",
           "ruled_sheet_tets", "tet_surface", "voxel_tets"]
