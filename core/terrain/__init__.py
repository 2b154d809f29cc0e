"""Ground, height above ground and canopy height models.

Everything here computes in the cloud's local metric frame
(:meth:`PointCloud.local_xyz`: metres, origin at the tile's lower-left) and
returns heights in **metres**, whatever the CRS units: a normalised cloud
carries one float64 attribute ``height`` (metres above ground); there is no
separate ``ground_z`` attribute, the ground elevation is ``z - height`` after
converting ``height`` to vertical CRS units.  Rasters come back in the cloud's
CRS (pixel size in CRS units = ``resolution_m / units.horizontal_m``) with
values in metres.

Ground classification, when a tile has none (class 2), is a method value passed
to :func:`classify_ground`:

* :class:`SMRF` — Pingel, Clarke & McBride (2013), "An improved simple
  morphological filter for the terrain classification of airborne LIDAR
  data", ISPRS J. Photogramm. Remote Sens. 77:21-30.
* :class:`CSF` — Zhang, Qi, Wan, Wang, Xie, Wang & Yan (2016), "An easy-to-use
  airborne LiDAR data filtering method based on cloth simulation", Remote
  Sensing 8(6):501.

The default (:data:`DEFAULT_GROUND`) was chosen by the comparison printed by
``benchmarks/terrain.py`` (ground precision/recall and DTM RMSE on synthetic
stands on 0, 15 and 30 degree slopes).

The pit-free CHM follows Khosravipour, Skidmore, Isenburg, Wang & Hussin
(2014), "Generating pit-free canopy height models from airborne lidar",
Photogramm. Eng. Remote Sens. 80(9):863-872: partial CHMs interpolated from
TINs of the first returns above a series of height thresholds, triangles with
an edge longer than a freeze distance removed from all but the lowest layer,
stacked by per-cell maximum.

Modules: :mod:`.ground` (the ground class, SMRF, CSF, :func:`classify_ground`), :mod:`.interpolation`
(the Delaunay TIN with its compiled point location, ground thinning, k-nearest IDW), :mod:`.heights`
(ground elevation, height above ground, :func:`normalize`) and :mod:`.rasters` (DTM and CHM); the
public names are re-exported here.
"""
from __future__ import annotations

from ..noise import NOISE_CLASSES
from .ground import (CSF, DEFAULT_GROUND, GROUND_CLASS, SMRF, GroundMethod, classify_ground, grid_index, ground_mask,
                     low_outliers)
from .heights import ground_elevation, height_above_ground, height_as_z, heights_above_ground, is_normalized, normalize
from .interpolation import idw, lowest_per_cell, tin_interpolate
from .rasters import canopy_height_model, digital_terrain_model

__all__ = [
    "GROUND_CLASS", "low_outliers", "SMRF", "CSF", "DEFAULT_GROUND", "ground_mask", "classify_ground",
    "ground_elevation", "height_above_ground", "is_normalized", "normalize",
    "digital_terrain_model", "canopy_height_model", "NOISE_CLASSES",
]
