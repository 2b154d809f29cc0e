"""The QGIS plugin object: registers the Processing provider, warns about missing packages, and on the first
load in the desktop compiles the numba kernels in a background task (plugin/warmup.py) with a message saying so."""
from __future__ import annotations

from qgis.core import QgsApplication

from . import deps


class SylvaPlugin:
    def __init__(self, iface):
        self.iface = iface  # None inside qgis_process
        self.provider = None
        self.warmup_task = None

    def initProcessing(self):  # noqa: N802 (QGIS's name)
        from ..processing.provider import SylvaProvider

        self.provider = SylvaProvider()
        QgsApplication.processingRegistry().addProvider(self.provider)

    def initGui(self):  # noqa: N802
        self.initProcessing()
        lacking = deps.missing()
        if lacking and self.iface is not None:
            self.iface.messageBar().pushWarning("Sylva", deps.install_hint(lacking))
        elif self.iface is not None:
            self._warm_up_once()

    def _warm_up_once(self):
        """First load after installing or updating: compile the kernels in the background, saying so."""
        from . import warmup

        if warmup.is_warm():
            return
        from qgis.core import Qgis, QgsTask

        bar = self.iface.messageBar()
        bar.pushMessage("Sylva", "Preparing Sylva's compiled routines for its first run (about a minute, once; "
                        "progress in the task bar). Sylva's algorithms work meanwhile, more slowly.",
                        Qgis.Info, 15)

        def work(task):
            return warmup.warm_up(progress=lambda f, m="": task.setProgress(100.0 * f),
                                  cancelled=task.isCanceled)

        def done(exception, result=None):
            if exception is None and result is not None:
                bar.pushMessage("Sylva", f"Sylva is ready: {result['compiled']} compiled routines cached in "
                                f"{result['seconds']:.0f} s.", Qgis.Success, 8)
            elif exception is not None:
                bar.pushWarning("Sylva", f"Preparing the compiled routines failed ({exception}); the first run "
                                "will compile them instead.")
            self.warmup_task = None

        self.warmup_task = QgsTask.fromFunction("Sylva: compiling routines for the first run", work,
                                                on_finished=done)
        QgsApplication.taskManager().addTask(self.warmup_task)

    def unload(self):
        if self.warmup_task is not None:
            try:
                self.warmup_task.cancel()
            except RuntimeError:  # already deleted by the task manager
                pass
            self.warmup_task = None
        if self.provider is not None:
            QgsApplication.processingRegistry().removeProvider(self.provider)
            self.provider = None
