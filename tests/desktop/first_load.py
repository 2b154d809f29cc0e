# Run inside the QGIS desktop (qgis --code THIS), started by tests/test_desktop_warmup.py under Xvfb, with an
# empty NUMBA_CACHE_DIR: the plugin's first load must say it prepares its compiled routines, do it in another
# process (no Python thread inside QGIS), keep the interface alive while a new 3D view opens, and say when it
# is done. Writes JSON to $SYLVA_DESKTOP_REPORT.
import json
import os
import time
import traceback

from qgis.core import QgsApplication, QgsCoordinateReferenceSystem, QgsProject
from qgis.PyQt.QtCore import QTimer
from qgis.PyQt.QtWidgets import QAction, QApplication
from qgis.utils import iface

REPORT = os.environ["SYLVA_DESKTOP_REPORT"]
T0 = time.time()
report = {"steps": [], "error": None}


def log(step):
    report["steps"].append([round(time.time() - T0, 1), step])
    with open(REPORT, "w") as fh:
        json.dump(report, fh, indent=1)


def bar_texts():
    return [f"{item.title()}: {item.text()}" for item in iface.messageBar().items()]


def warmup_processes():
    found = []
    for pid in os.listdir("/proc"):
        if pid.isdigit():
            try:
                with open(f"/proc/{pid}/cmdline", "rb") as fh:
                    cmd = fh.read().replace(b"\0", b" ").decode("utf-8", "replace")
            except OSError:
                continue
            if "sylva.plugin.warmup" in cmd:
                found.append(cmd.strip())
    return found


def start():
    try:
        report["bar_at_start"] = bar_texts()
        report["processes_at_start"] = warmup_processes()
        report["python_threads"] = QgsApplication.taskManager().countActiveTasks()
        log("checked the start")
        QgsProject.instance().setCrs(QgsCoordinateReferenceSystem("EPSG:32632"))  # a 3D view needs a projected CRS
        QTimer.singleShot(1500, modal)          # new3DMapCanvas() asks for a name (a modal dialog) first
        iface.mainWindow().findChild(QAction, "mActionNew3DMapCanvas").trigger()
        QApplication.processEvents()
        log("3D view opened")
        QTimer.singleShot(2000, alive)
    except Exception:
        report["error"] = traceback.format_exc()[-2000:]
        log("failed")
        QgsApplication.exit(1)


def modal():
    dialog = QApplication.activeModalWidget()
    if dialog is not None:
        text = dialog.text() if hasattr(dialog, "text") else ""
        report.setdefault("modal", []).append(f"{type(dialog).__name__}: {text}")
        dialog.accept()


def alive():
    report["processes_after_3d"] = warmup_processes()
    log("interface alive after the 3D view opened")
    poll()


def poll():
    if warmup_processes() and time.time() - T0 < 400:
        QTimer.singleShot(1000, poll)
        return
    QTimer.singleShot(1500, finish)      # the finished signal's message


def finish():
    report["bar_at_end"] = bar_texts()
    log("done")
    QgsApplication.exit(0)


QTimer.singleShot(3000, start)
