"""The QGIS plugin object: registers the Processing provider, warns about missing packages."""
from __future__ import annotations

from qgis.core import QgsApplication

from . import deps


class SylvaPlugin:
    def __init__(self, iface):
        self.iface = iface  # None inside qgis_process
        self.provider = None

    def initProcessing(self):  # noqa: N802 (QGIS's name)
        from ..processing.provider import SylvaProvider

        self.provider = SylvaProvider()
        QgsApplication.processingRegistry().addProvider(self.provider)

    def initGui(self):  # noqa: N802
        self.initProcessing()
        lacking = deps.missing()
        if lacking and self.iface is not None:
            self.iface.messageBar().pushWarning("Sylva", deps.install_hint(lacking))

    def unload(self):
        if self.provider is not None:
            QgsApplication.processingRegistry().removeProvider(self.provider)
            self.provider = None
