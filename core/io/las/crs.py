"""The CRS and units of a LAS/LAZ header: WKT or GeoTIFF VLRs (:func:`parse_crs`), units (:func:`units_of`).

A CRS the caller passes overrides the file's (:func:`crs_and_units`); a geographic CRS is refused
(:func:`require_linear`), and so is a cloud without one where one is needed (:func:`require_crs`).
"""
from __future__ import annotations

import math

from ...cloud import INTERNATIONAL_FOOT, METRE, METRES, US_SURVEY_FOOT, PointCloud, Units
from ...errors import CRSError

# EPSG unit-of-measure codes used by the GeoTIFF keys, as metres per unit.
_EPSG_LINEAR_UNITS = {9001: METRE, 9002: INTERNATIONAL_FOOT, 9003: US_SURVEY_FOOT}
_GEOKEY_PROJ_LINEAR_UNITS = 3076
_GEOKEY_VERTICAL_CS = 4096
_GEOKEY_VERTICAL_UNITS = 4099


def _snap_unit(factor: float) -> float:
    for known in (METRE, INTERNATIONAL_FOOT, US_SURVEY_FOOT):
        if abs(factor - known) <= 1e-12 * known:
            return known
    return float(factor)


def units_of(crs) -> Units:
    """Metres per unit of the horizontal and vertical axes of a pyproj CRS.

    Horizontal: the unit of the horizontal (projected) part.  Vertical: the
    unit of the vertical part of a compound CRS, or of the third axis of a 3D
    CRS, else the horizontal unit.  A geographic horizontal CRS has no linear
    unit: its horizontal factor is NaN (and its vertical unit metres unless
    the CRS says otherwise).  ``None`` gives metres.
    """
    if crs is None:
        return METRES
    if getattr(crs, "is_bound", False):
        crs = crs.source_crs
    horizontal, vertical = crs, None
    if crs.is_compound:
        horizontal = None
        for sub in crs.sub_crs_list:
            if sub.is_bound:
                sub = sub.source_crs
            if sub.is_vertical:
                vertical = vertical or sub
            elif horizontal is None:
                horizontal = sub
    elif crs.is_vertical:
        horizontal, vertical = None, crs

    h_m = METRE
    axes = list(horizontal.axis_info) if horizontal is not None else []
    if horizontal is not None and horizontal.is_geographic:
        h_m = math.nan
    elif axes:
        h_m = _snap_unit(axes[0].unit_conversion_factor)

    if vertical is not None and vertical.axis_info:
        v_m = _snap_unit(vertical.axis_info[0].unit_conversion_factor)
    elif len(axes) >= 3 and axes[2].direction.lower() in ("up", "down"):
        v_m = _snap_unit(axes[2].unit_conversion_factor)
    elif math.isnan(h_m):
        v_m = METRE
    else:
        v_m = h_m
    return Units(horizontal_m=h_m, vertical_m=v_m)


def as_crs(crs, where: str):
    """A pyproj CRS from anything pyproj accepts ("EPSG:2994", 26912, WKT, CRS)."""
    if crs is None:
        return None
    import pyproj

    if isinstance(crs, pyproj.CRS):
        return crs
    try:
        return pyproj.CRS.from_user_input(crs)
    except Exception as err:  # pyproj.exceptions.CRSError and friends
        raise CRSError(f"{where}: the CRS {crs!r} given is not understood ({err})") from None


def _geokeys(header) -> dict:
    """GeoTIFF keys stored inline (tiff_tag_location 0) as {key id: value}."""
    try:
        vlr = header.vlrs.get("GeoKeyDirectoryVlr")
    except Exception:
        return {}
    keys = {}
    for v in vlr:
        for k in getattr(v, "geo_keys", []):
            if k.tiff_tag_location == 0 and k.id:
                keys[int(k.id)] = int(k.value_offset)
    return keys


def parse_crs(header, where: str = "the LAS file"):
    """The CRS of a laspy header (WKT preferred over GeoTIFF keys) or None.

    A GeoTIFF vertical CRS key (VerticalCSTypeGeoKey, an EPSG code) is joined
    to the horizontal CRS as a compound CRS.  A CRS record that exists but
    cannot be understood raises :class:`CRSError`.
    """
    import pyproj

    has_wkt = bool(header.vlrs.get("WktCoordinateSystemVlr"))
    try:
        crs = header.parse_crs()
    except Exception as err:
        raise CRSError(
            f"{where}: its CRS record cannot be understood ({err}); "
            "pass a CRS with the CRS parameter"
        ) from None
    if crs is not None and not has_wkt and not crs.is_compound:
        code = _geokeys(header).get(_GEOKEY_VERTICAL_CS)
        if code is not None and 1024 <= code <= 32766:
            try:
                vertical = pyproj.CRS.from_epsg(code)
                crs = pyproj.CRS.from_user_input(
                    pyproj.crs.CompoundCRS(f"{crs.name} + {vertical.name}", [crs, vertical])
                )
            except Exception:
                pass  # an unknown vertical code: keep the horizontal CRS
    return crs


def _units_from_header(header, crs, from_file: bool) -> Units:
    units = units_of(crs)
    if not from_file:
        return units
    keys = _geokeys(header)
    if crs is None:
        h = _EPSG_LINEAR_UNITS.get(keys.get(_GEOKEY_PROJ_LINEAR_UNITS), METRE)
        v = _EPSG_LINEAR_UNITS.get(keys.get(_GEOKEY_VERTICAL_UNITS), h)
        return Units(horizontal_m=h, vertical_m=v)
    if not crs.is_compound and _GEOKEY_VERTICAL_UNITS in keys:
        v = _EPSG_LINEAR_UNITS.get(keys[_GEOKEY_VERTICAL_UNITS])
        if v is not None:
            return Units(horizontal_m=units.horizontal_m, vertical_m=v)
    return units


def crs_and_units(header, crs, where, units=None):
    """(crs, units, parsed-from-file crs) for a header and optional overrides."""
    if crs is not None:
        crs = as_crs(crs, where)
        parsed = None
    else:
        crs = parsed = parse_crs(header, where)
    if units is not None:
        if not isinstance(units, Units):
            units = Units(horizontal_m=float(units), vertical_m=float(units))
        return crs, units, parsed
    if crs is not None and parsed is None:  # an override: its own units
        return crs, units_of(crs), None
    return crs, _units_from_header(header, parsed, True), parsed


def require_linear(units: Units, crs, where: str) -> None:
    """Refuse a geographic (degree) CRS: Sylva computes in metres from x/y in
    metres or feet, and does not reproject."""
    if math.isnan(units.horizontal_m):
        name = crs.name if crs is not None else "geographic"
        raise CRSError(
            f"{where}: its CRS ({name}) is geographic, in degrees; Sylva needs projected "
            "coordinates in metres or feet: reproject the file first, or pass the right "
            "CRS with the CRS parameter"
        )


def require_crs(cloud: PointCloud) -> PointCloud:
    """Return ``cloud`` if it has a CRS, else raise :class:`CRSError` naming its file."""
    if cloud.crs is None:
        raise CRSError(f"{cloud.name} has no CRS; pass one with the CRS parameter")
    return cloud
