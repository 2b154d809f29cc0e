"""The `sylva` Processing provider: one algorithm per entry of sylva.algorithms."""
from __future__ import annotations

from pathlib import Path

from qgis.core import Qgis, QgsMessageLog, QgsProcessingProvider
from qgis.PyQt.QtGui import QIcon

from ..plugin import deps

ICON = Path(__file__).resolve().parents[1] / "resources" / "icon.svg"


class SylvaProvider(QgsProcessingProvider):
    def id(self):
        return "sylva"

    def name(self):
        return "Sylva"

    def longName(self):  # noqa: N802
        return "Sylva: individual trees and 3D tree models from LiDAR"

    def icon(self):
        return QIcon(str(ICON))

    def loadAlgorithms(self):  # noqa: N802
        lacking = deps.missing()
        if lacking:
            # Load anyway, with one algorithm that tells the user what to install.
            from .algorithm import MissingDependencies

            QgsMessageLog.logMessage(deps.install_hint(lacking), "Sylva", Qgis.Critical)
            self.addAlgorithm(MissingDependencies(lacking))
            return
        from ..algorithms import all_algorithms
        from .algorithm import SylvaAlgorithm

        for spec in all_algorithms().values():
            self.addAlgorithm(SylvaAlgorithm(spec))
