"""Voxel reconstruction core (thesis §2.2.4, Caillette et al. §6.1): the voxel grid,
projection look-up tables, shape from silhouette (flat and coarse-to-fine), voxel
colouring with visibility and the surface set. Pure numpy/numba, no messaging."""
from .colouring import COLOURINGS, VoxelColourer, boundary_voxels
from .grid import BrickLayout, VoxelGrid
from .projection import ProjectionTable
from .reconstructor import METHODS, PIPELINE_CARVING, Reconstructor

__all__ = ["VoxelGrid", "BrickLayout", "ProjectionTable", "VoxelColourer", "Reconstructor", "boundary_voxels",
           "METHODS", "COLOURINGS", "PIPELINE_CARVING"]
