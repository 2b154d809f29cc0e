"""GeoPackage layers with GDAL/OGR: conforming files, R-tree indexes, QGIS styles, bulk rows.

    write_gpkg("out.gpkg", [tops, crowns], styles={"crowns": "crowns.qml"})
    write_gpkg("out.gpkg", [trees], update=True)       # add/replace a layer, keep the others
    table = read_layer("out.gpkg|layername=crowns")

GDAL/OGR (``osgeo``: Debian's python3-gdal, in every QGIS install) creates
each file and layer: the metadata tables, the SRS, the geometry column
declared with its type (OGC 12-128r18 Req 25/31), ``gpkg_ogr_contents``;
``validate_gpkg.py`` (GDAL's validator) reports no failure on what is
written here.  The rows are then inserted with SQLite in bulk, many rows per
statement (OGR's per-feature ``CreateFeature`` from Python costs ~30 us a
feature, 20x this; GDAL 3.6 has no Arrow writing), and every geometry
column gets the GeoPackage R-tree extension (``gpkg_rtree_index``, Annex
F.3): the ``rtree_<table>_<column>`` table bulk-loaded from the
geometries' envelopes (sort-tile-recursive packing written straight into the
R-tree's node tables, ~1 us a feature; an R-tree ``INSERT`` costs ~20 us)
and GDAL's seven triggers, so QGIS and GDAL keep it current on later edits.
Styles go into QGIS's ``layer_styles`` table, so a file opens styled in any
QGIS.  Files are written under a temporary name and renamed when complete.
Layer and column names are always quoted as SQL identifiers or bound.
(Sylva, not in the papers.)

Modules: :mod:`.gdal` (GDAL's bindings, messages and options), :mod:`.sqlite` (quoted identifiers, page size, bulk
rows), :mod:`.write` (:func:`write_gpkg`), :mod:`.rtree` (envelopes and R-trees), :mod:`.styles` (``layer_styles``),
:mod:`.merge` (:class:`GpkgMerge`) and :mod:`.read` (:func:`read_gpkg`, :func:`read_layer`); the public names are
re-exported here.
"""
from __future__ import annotations

from .gdal import ConfigOptions, GdalErrors, bindings
from .merge import MERGE_MMAP_BYTES, GpkgMerge
from .read import layer_names, read_gpkg, read_layer, split_source
from .rtree import add_rtree, blob_bounds, outward_float32, read_rtree
from .sqlite import MAX_VARIABLES, PAGE_SIZE, insert_rows, quote
from .styles import STYLES, default_styles, write_styles
from .write import write_gpkg

__all__ = ["write_gpkg", "read_gpkg", "read_layer", "layer_names", "GpkgMerge", "STYLES", "quote",
           "split_source", "PAGE_SIZE"]
