"""GDAL's Python bindings (``osgeo``), imported when first needed, and its messages and options scoped to a call."""
from __future__ import annotations

from ...errors import SylvaError


def bindings():
    try:
        from osgeo import gdal, ogr, osr
    except ImportError:
        raise SylvaError("GeoPackage output needs GDAL's Python bindings (osgeo): install python3-gdal "
                         "(Debian/Ubuntu, as QGIS does) or the GDAL wheel matching the system's GDAL") from None
    return gdal, ogr, osr


class GdalErrors:
    """Collect GDAL's messages quietly (no global UseExceptions, which would change QGIS's GDAL for others)."""

    def __enter__(self):
        gdal = bindings()[0]
        self.gdal = gdal
        gdal.PushErrorHandler("CPLQuietErrorHandler")
        gdal.ErrorReset()
        return self

    def message(self) -> str:
        return self.gdal.GetLastErrorMsg() or "unknown GDAL error"

    def __exit__(self, *exc):
        self.gdal.PopErrorHandler()
        return False


class ConfigOptions:
    """GDAL configuration options for this thread only, restored afterwards."""

    def __init__(self, **options):
        self.options = options

    def __enter__(self):
        gdal = bindings()[0]
        self.gdal = gdal
        self.old = {k: gdal.GetThreadLocalConfigOption(k, None) for k in self.options}
        for k, v in self.options.items():
            gdal.SetThreadLocalConfigOption(k, v)
        return self

    def __exit__(self, *exc):
        for k, v in self.old.items():
            self.gdal.SetThreadLocalConfigOption(k, v)
        return False
