"""Sylva: individual trees and 3D tree models from LiDAR, as a QGIS plugin.

This module holds only :func:`classFactory`, which QGIS calls; it imports
nothing from qgis at module level so that ``import sylva.core`` works in a
plain Python without QGIS.
"""


def classFactory(iface):  # noqa: N802 (QGIS's name)
    """QGIS entry point: return the plugin object (``iface`` is None in qgis_process)."""
    from .plugin.main import SylvaPlugin

    return SylvaPlugin(iface)
