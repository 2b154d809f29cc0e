"""The QGIS plugin object: registers the Processing provider, warns about missing packages, and on the first
load in the desktop compiles the numba kernels in a separate Python process (plugin/warmup.py) with a message
and a progress bar saying so."""
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
        """First load after installing or updating: compile the kernels, saying so, in a separate Python process
        (``python -m sylva.plugin.warmup``) that writes the cache this QGIS then loads.

        Not a QgsTask: a task holds a thread of Qt's global pool for the minute it compiles, and QGIS 3.22's
        3D view, created meanwhile, waits for every thread of that pool (Qt3D's ``QAspectEngine``) and
        freezes; the compiling would also hold this process's Python lock against the interface."""
        import os

        from . import warmup

        if warmup.is_warm():
            return
        from qgis.core import Qgis
        from qgis.PyQt.QtCore import QProcess, QProcessEnvironment
        from qgis.PyQt.QtWidgets import QProgressBar

        bar = self.iface.messageBar()
        item = bar.createMessage("Sylva", "Preparing Sylva's compiled routines for its first run (about a minute, "
                                 "once). Sylva's algorithms work meanwhile, more slowly.")
        meter = QProgressBar()
        meter.setRange(0, 100)
        item.layout().addWidget(meter)
        bar.pushWidget(item, Qgis.Info)
        # import Sylva through the path QGIS loaded it from: numba keys a NUMBA_CACHE_DIR cache by that path
        plugins = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        env = QProcessEnvironment.systemEnvironment()
        env.insert("PYTHONPATH", os.pathsep.join(p for p in (plugins, env.value("PYTHONPATH")) if p))
        proc = QProcess()
        proc.setProcessEnvironment(env)
        proc.setProcessChannelMode(QProcess.MergedChannels)
        lines = []

        def read():
            text = bytes(proc.readAllStandardOutput()).decode("utf-8", "replace")
            for line in text.splitlines():
                lines.append(line)
                if line.startswith("progress "):
                    try:
                        meter.setValue(int(100 * float(line.split()[1])))
                    except (IndexError, ValueError):
                        pass

        def done(code, status):
            read()
            try:
                bar.popWidget(item)
            except RuntimeError:  # already closed by the user
                pass
            if status == QProcess.NormalExit and code == 0:
                summary = next((ln for ln in reversed(lines) if ln.startswith("sylva warm-up:")), "done")
                bar.pushMessage("Sylva", "Sylva is ready: " + summary.split(":", 1)[1].strip(), Qgis.Success, 8)
            else:
                tail = " ".join(ln for ln in lines[-3:] if not ln.startswith("progress "))
                bar.pushWarning("Sylva", f"Preparing the compiled routines failed ({tail or f'exit {code}'}); "
                                "the first run will compile them instead.")
            self.warmup_task = None

        proc.readyReadStandardOutput.connect(read)
        proc.finished.connect(done)
        proc.start(deps.interpreter(), ["-m", "sylva.plugin.warmup", "--if-needed", "--progress"])
        self.warmup_task = proc

    def unload(self):
        if self.warmup_task is not None:
            try:
                self.warmup_task.kill()         # the warm-up process; the cache it wrote so far stays valid
                self.warmup_task.waitForFinished(3000)
            except RuntimeError:  # already deleted
                pass
            self.warmup_task = None
        if self.provider is not None:
            QgsApplication.processingRegistry().removeProvider(self.provider)
            self.provider = None
