# Run inside QGIS desktop (xvfb-run qgis --code THIS): scripts/render_3d.py and tests/test_desktop_outputs.py do.
#
# 1. Opens sylva:pipeline's dialog with INPUT and OUTPUT_FOLDER filled in and presses Run (the dialog's own
#    runAlgorithm: a background task, then Processing's handling of the results, as for a user).
# 2. Records the layers that appear in the project: name, source, type, 2D renderer, 3D renderer, visibility.
# 3. Saves the map canvas (the styled crowns over the CHM) and opens a NEW 3D map view (the menu action
#    View > New 3D Map View) with its default camera, grabs it, hides crowns_3d and grabs it again, hides
#    models_3d too and grabs it once more.
# 4. Starts a new project, runs sylva:exportmodels' dialog on the run's GLB (MODELS_3D and CROWNS_3D to one
#    GeoPackage)
#    and grabs a new 3D view of what it loads.
# Writes a JSON report to $SYLVA_REPORT and PNGs into $SYLVA_SHOTS.
import json
import os
import time
import traceback

from qgis.core import QgsApplication, QgsProject
from qgis.PyQt.QtCore import QTimer
from qgis.PyQt.QtWidgets import QAction, QApplication, QDockWidget, QWidget
from qgis.utils import iface

REPORT = os.environ["SYLVA_REPORT"]
SAMPLE = os.environ["SYLVA_SAMPLE"]
OUT = os.environ["SYLVA_OUT"]
SHOTS = os.environ["SYLVA_SHOTS"]
report = {"steps": [], "error": None}


def log(step):
    report["steps"].append([round(time.time() - T0, 1), step])
    save()


def save():
    with open(REPORT, "w") as fh:
        json.dump(report, fh, indent=1)


def wait_until(predicate, timeout_s, then, on_timeout):
    start = time.time()

    def poll():
        try:
            if predicate():
                then()
            elif time.time() - start > timeout_s:
                on_timeout()
            else:
                QTimer.singleShot(500, poll)
        except Exception:
            fail()
    poll()


def fail():
    report["error"] = traceback.format_exc()[-3000:]
    save()
    QgsApplication.exit(1)


def finish():
    log("done")
    QgsApplication.exit(0)


def layers_info():
    out = []
    root = QgsProject.instance().layerTreeRoot()
    for node in root.findLayers():
        layer = node.layer()
        r2 = layer.renderer().type() if hasattr(layer, "renderer") and layer.renderer() is not None else None
        r3 = layer.renderer3D().type() if layer.renderer3D() is not None else None
        out.append({"name": layer.name(), "source": layer.source(), "type": int(layer.type()),
                    "renderer": r2, "renderer3d": r3, "visible": node.isVisible(),
                    "features": layer.featureCount() if hasattr(layer, "featureCount") else None})
    return out


def grab(widget, path):
    QApplication.processEvents()
    QApplication.primaryScreen().grabWindow(0, *_rect(widget)).save(path)
    return path


def new_3d_view():
    """Trigger View > New 3D Map View; return its dock widget (floating, 1200 x 800)."""
    from qgis.PyQt import sip

    # docks are told apart by their C++ address: Python's id() of a wrapper findChildren made may be reused
    # once it is collected, and then every dock looks new (a fresh profile grabbed the Layer Styling dock)
    before = {sip.unwrapinstance(d) for d in iface.mainWindow().findChildren(QDockWidget)}
    action = iface.mainWindow().findChild(QAction, "mActionNew3DMapCanvas")
    action.trigger()
    QApplication.processEvents()
    docks = [d for d in iface.mainWindow().findChildren(QDockWidget)
             if sip.unwrapinstance(d) not in before and d.windowTitle().startswith("3D Map")]
    if not docks:
        raise RuntimeError("no 3D map view dock appeared")
    dock = docks[-1]
    dock.setFloating(True)
    dock.setGeometry(40, 40, 1200, 800)
    dock.show()
    return dock


def view_3d_widget(dock):
    """The 3D canvas inside the dock: the sibling of the navigation panel (the one with "Show camera info")."""
    from qgis.PyQt.QtWidgets import QCheckBox

    boxes = [b for b in dock.findChildren(QCheckBox) if "camera" in b.text().lower()]
    if boxes:
        nav = boxes[0].parentWidget()
        siblings = [w for w in nav.parentWidget().findChildren(QWidget) if w.parentWidget() is nav.parentWidget()
                    and w is not nav and w.isVisible()]
        if siblings:
            return max(siblings, key=lambda w: w.width() * w.height())
    return dock


def when_drawn(dock, then, timeout_s=120.0):
    """Call ``then`` once two grabs of the 3D canvas 3 s apart are the same and not blank (scene loaded)."""
    start = time.time()
    last = [None]

    def poll():
        try:
            image = QApplication.primaryScreen().grabWindow(0, *_rect(view_3d_widget(dock))).toImage()
            same = last[0] is not None and image == last[0]
            colours = len({image.pixel(x, y) for x in range(0, image.width(), 17) for y in range(0, image.height(), 17)})
            last[0] = image
            if (same and colours > 8) or time.time() - start > timeout_s:
                report.setdefault("waits_3d_s", []).append(round(time.time() - start, 1))
                then()
            else:
                QTimer.singleShot(3000, poll)
        except Exception:
            fail()
    QTimer.singleShot(3000, poll)


def _rect(widget):
    top_left = widget.mapToGlobal(widget.rect().topLeft())
    return top_left.x(), top_left.y(), widget.width(), widget.height()


def step_run_pipeline():
    import processing

    log("opening the pipeline dialog")
    dlg = processing.createAlgorithmDialog("sylva:pipeline", {"INPUT": SAMPLE, "OUTPUT_FOLDER": OUT})
    dlg.show()
    report["dialog"] = "pipeline"
    QApplication.processEvents()
    grab(dlg, os.path.join(SHOTS, "pipeline_dialog.png"))
    dlg.runAlgorithm()
    log("Run pressed")
    wait_until(lambda: len(QgsProject.instance().mapLayers()) >= 10, 900, lambda: after_pipeline(dlg),
               lambda: timeout("pipeline layers"))


def timeout(what):
    report["error"] = f"timeout waiting for {what}; layers: {[l['name'] for l in layers_info()]}"
    report["layers"] = layers_info()
    save()
    QgsApplication.exit(1)


def after_pipeline(dlg):
    log("layers loaded")
    QApplication.processEvents()
    grab(dlg, os.path.join(SHOTS, "pipeline_dialog_done.png"))
    dlg.close()
    report["layers"] = layers_info()
    canvas = iface.mapCanvas()
    canvas.zoomToFullExtent()
    canvas.refreshAllLayers()
    wait_until(lambda: not canvas.isDrawing(), 60, lambda: QTimer.singleShot(2000, map_2d), lambda: map_2d())


def map_2d():
    iface.mapCanvas().saveAsImage(os.path.join(SHOTS, "crowns_2d.png"))
    QApplication.primaryScreen().grabWindow(0).save(os.path.join(SHOTS, "desktop_after_pipeline.png"))
    log("2D map saved")
    when_no_tasks(open_3d_view)


def when_no_tasks(then, timeout_s=600.0):
    """Call ``then`` once no QgsTask runs.  A Python task (as the plugin's first-load warm-up was before it
    moved to a process of its own, plugin/main.py) running while a 3D view is created deadlocks QGIS 3.22: the main thread, holding Python's GIL, waits in
    Qt3D's ``QAspectEngine::setRootEntity`` for a function to run on every pooled thread, and the task's
    thread waits for the GIL (seen with gdb)."""
    start = time.time()
    wait_until(lambda: QgsApplication.taskManager().countActiveTasks() == 0, timeout_s,
               lambda: (report.setdefault("waits_tasks_s", []).append(round(time.time() - start, 1)), then()),
               then)


def open_3d_view():
    dock = new_3d_view()
    report["view3d_dock"] = dock.windowTitle()
    when_drawn(dock, lambda: shot_3d(dock))


def shot_3d(dock):
    try:
        widget = view_3d_widget(dock)
        report["view3d_widget"] = [type(widget).__name__, widget.width(), widget.height()]
        grab(widget, os.path.join(SHOTS, "view3d_pipeline.png"))
        QApplication.primaryScreen().grabWindow(0).save(os.path.join(SHOTS, "desktop_3d.png"))
        log("3D view grabbed")
        hide("crowns_3d")
        when_drawn(dock, lambda: shot_3d_no_crowns(dock))
    except Exception:
        fail()


def hide(name):
    layers = QgsProject.instance().mapLayersByName(name)
    QgsProject.instance().layerTreeRoot().findLayer(layers[0].id()).setItemVisibilityChecked(False)


def shot_3d_no_crowns(dock):
    try:
        grab(view_3d_widget(dock), os.path.join(SHOTS, "view3d_pipeline_no_crowns.png"))
        log("3D view without crowns grabbed")
        hide("models_3d")
        when_drawn(dock, lambda: shot_3d_without(dock))
    except Exception:
        fail()


def shot_3d_without(dock):
    try:
        grab(view_3d_widget(dock), os.path.join(SHOTS, "view3d_pipeline_no_models.png"))
        log("3D view without models grabbed")
        dock.close()
        step_exportmodels()
    except Exception:
        fail()


def step_exportmodels():
    import processing

    QgsProject.instance().clear()
    glb = os.path.join(OUT, "models", os.path.splitext(os.path.basename(SAMPLE))[0] + ".glb")
    target = os.path.join(os.path.dirname(OUT), "exported_3d.gpkg")
    dlg = processing.createAlgorithmDialog("sylva:exportmodels", {"INPUT": glb, "MODELS_3D": target,
                                                                  "CROWNS_3D": target})
    dlg.show()
    dlg.runAlgorithm()
    log("exportmodels Run pressed")
    wait_until(lambda: len(QgsProject.instance().mapLayers()) >= 2, 300, lambda: after_export(dlg),
               lambda: timeout("exportmodels layer"))


def after_export(dlg):
    dlg.close()
    report["export_layers"] = layers_info()
    iface.mapCanvas().zoomToFullExtent()
    when_no_tasks(lambda: export_3d_view())


def export_3d_view():
    dock = new_3d_view()
    when_drawn(dock, lambda: shot_export(dock))


def shot_export(dock):
    try:
        grab(view_3d_widget(dock), os.path.join(SHOTS, "view3d_exportmodels.png"))
        log("exportmodels 3D view grabbed")
        dock.close()
        finish()
    except Exception:
        fail()


def start():
    try:
        step_run_pipeline()
    except Exception:
        fail()


T0 = time.time()
QTimer.singleShot(3000, start)
