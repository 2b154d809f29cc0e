"""The `sylva` Processing provider: one algorithm per entry of sylva.algorithms."""
from __future__ import annotations

from pathlib import Path

from qgis.core import QgsProcessingProvider
from qgis.PyQt.QtGui import QIcon

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
        from ..algorithms import ALGORITHMS
        from .algorithm import SylvaAlgorithm

        for spec in ALGORITHMS.values():
            self.addAlgorithm(SylvaAlgorithm(spec))
