"""Reading: any GeoPackage layer through OGR, named by file and layer or as QGIS names a source."""
from __future__ import annotations

from pathlib import Path
from typing import List

import numpy as np
import shapely

from ...errors import InputError
from ...table import VectorTable
from .gdal import GdalErrors, bindings

def split_source(source: str) -> tuple:
    """(path, layer name or None) of a QGIS-style source ``file.gpkg`` or ``file.gpkg|layername=NAME``."""
    path, _, options = str(source).partition("|")
    layer = None
    for option in filter(None, options.split("|")):
        key, _, value = option.partition("=")
        if key.strip().lower() == "layername":
            layer = value.strip()
    return path, layer


def _open(path) -> object:
    gdal, ogr, _ = bindings()
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: file not found")
    with GdalErrors() as err:
        ds = gdal.OpenEx(str(path), gdal.OF_VECTOR | gdal.OF_READONLY, allowed_drivers=["GPKG"])
        if ds is None:
            raise InputError(f"{path}: not a GeoPackage ({err.message()})")
    return ds


def layer_names(path) -> List[str]:
    """The names of the feature and attribute layers of a GeoPackage (not ``layer_styles``), in file order."""
    ds = _open(path)
    return [ds.GetLayer(i).GetName() for i in range(ds.GetLayerCount())
            if ds.GetLayer(i).GetName() != "layer_styles"]


def read_gpkg(path, layer: str) -> VectorTable:
    """Read one layer of a GeoPackage through OGR (any GeoPackage layer, not only Sylva's)."""
    import pyproj

    _, ogr, osr = bindings()
    path = Path(path)
    ds = _open(path)
    lay = ds.GetLayerByName(layer)
    if lay is None or lay.GetName() != layer:
        raise InputError(f"{path}: no layer named {layer!r}")
    defn = lay.GetLayerDefn()
    gtype = lay.GetGeomType()
    kind = "none" if gtype == ogr.wkbNone else _geometry_kind(ogr.GeometryTypeToName(gtype))
    has_z, has_m = bool(ogr.GT_HasZ(gtype)), bool(ogr.GT_HasM(gtype))
    crs = None
    srs = lay.GetSpatialRef()
    if srs is not None:
        code = srs.GetAuthorityCode(None) if srs.GetAuthorityName(None) == "EPSG" else None
        crs = pyproj.CRS.from_epsg(int(code)) if code else pyproj.CRS.from_wkt(srs.ExportToWkt(["FORMAT=WKT2_2018"]))
    fields = [defn.GetFieldDefn(i) for i in range(defn.GetFieldCount())]
    values = [[] for _ in fields]
    wkb = []
    with GdalErrors() as err:
        lay.ResetReading()
        for feature in lay:
            for i, column in enumerate(values):
                column.append(feature.GetField(i) if feature.IsFieldSetAndNotNull(i) else None)
            if kind != "none":
                g = feature.GetGeometryRef()
                wkb.append(None if g is None else bytes(g.ExportToIsoWkb()))
        if err.gdal.GetLastErrorType() >= 3:
            raise InputError(f"{path}: cannot read layer {layer!r} ({err.message()})")
    columns = {}
    for f, column in zip(fields, values):
        columns[f.GetName()] = _column(column, f.GetType(), ogr)
    geoms = None
    if kind != "none":
        if has_m:
            geoms = np.array(wkb, dtype=object)
        else:
            geoms = shapely.from_wkb(np.array(wkb, dtype=object))
    return VectorTable(layer, kind, geoms, columns, crs, has_z=has_z or kind == "none", has_m=has_m,
                       wkb=has_m)


def _geometry_kind(name: str) -> str:
    """"point" | "line" | "polygon" for an OGR geometry type name (Multi- and Z/M forms too)."""
    name = name.upper()
    for word, kind in (("POINT", "point"), ("LINE", "line"), ("CURVE", "line"), ("POLYGON", "polygon"),
                       ("SURFACE", "polygon")):
        if word in name:
            return kind
    return "polygon"


def _column(vals: list, ftype: int, ogr) -> np.ndarray:
    if ftype in (ogr.OFTInteger, ogr.OFTInteger64) and all(v is not None for v in vals):
        return np.array(vals, dtype=np.int64)
    if ftype in (ogr.OFTInteger, ogr.OFTInteger64, ogr.OFTReal):
        return np.array([np.nan if v is None else v for v in vals], dtype=np.float64)
    return np.array(vals, dtype=object)


def read_layer(source: str) -> VectorTable:
    """A vector layer named as QGIS names it: ``file.gpkg`` (its only layer) or ``file.gpkg|layername=NAME``."""
    path, layer = split_source(source)
    if layer is None:
        names = layer_names(path)
        if len(names) != 1:
            raise InputError(f"{path}: holds {len(names)} layers ({', '.join(names) or 'none'}); "
                             f"name one as {path}|layername=NAME")
        layer = names[0]
    return read_gpkg(path, layer)
