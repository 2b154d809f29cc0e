"""Quantitative structure models (QSM): cylinder and branch tables and tree measurements.

The output follows TreeQSM (Raumonen et al. 2013, Remote Sens. 5, 491–520):
a tree is a list of cylinders, each with its parent cylinder, its branch
and branch order, start point, unit axis, length and radius; branches are
runs of cylinders; per tree a DBH, height, trunk and total wood volume and
branch counts by order.  Sylva builds the cylinders from the sampled
B-spline centre lines of Yan et al. 2009 §4 (:mod:`sylva.core.reconstruct.kmeans`),
but :func:`cylinders_from_curves` takes any list of centre lines + radii, and
:func:`cylinders_from_skeleton` any skeleton with radii (one cylinder per edge).
:func:`refit_radii` fits each cylinder's radius and axis offset to the points
nearest it, :func:`taper_radii` keeps branches no thicker than their parent,
:func:`surface_distance` measures points against a model.

DBH (:func:`measure_qsm`): the points within ``band_m`` of 1.3 m above the
stem base and within 2 stem radii (+5 cm) of the stem axis there are fitted
with a circle (:func:`sylva.core.measure.fit_stem_circle`; up to three
passes dropping points more than 2 RMS, at least 1 cm, off it) under the
:class:`~sylva.core.measure.DbhRule` acceptance tests; ``dbh_source`` is then
``"measured"``, else the stem cylinder's diameter at 1.3 m is used
(``"cylinder"``).  Volumes are sums of ``π r² L``.

Tables are :class:`~sylva.core.table.VectorTable` (cylinders as 3-D lines
from start to end, or without geometry) and CSV files written atomically.

Modules: :mod:`.cylinders` (cylinder tables, radii, distances), :mod:`.measure` (branches, DBH,
volumes: :class:`QSM`), :mod:`.tables` (tables and CSV).  Synthetic cylinder trees for tests and
benchmarks are in :mod:`sylva.testing.cylinders`.
"""
from .cylinders import (CYLINDER_FIELDS, cylinders_from_curves, cylinders_from_skeleton, group_median,
                        refit_radii, surface_distance, taper_radii)
from .measure import BRANCH_FIELDS, QSM, branch_table_arrays, measure_qsm, skeleton_qsms
from .tables import (branches_table, cylinders_table, trees_table, write_branches_csv, write_cylinders_csv,
                     write_table_csv, write_trees_csv)

__all__ = ["QSM", "cylinders_from_curves", "cylinders_from_skeleton", "branch_table_arrays", "measure_qsm",
           "cylinders_table", "branches_table", "trees_table", "write_cylinders_csv",
           "write_branches_csv", "write_trees_csv", "write_table_csv", "surface_distance", "refit_radii",
           "taper_radii", "CYLINDER_FIELDS", "BRANCH_FIELDS", "skeleton_qsms", "group_median"]
