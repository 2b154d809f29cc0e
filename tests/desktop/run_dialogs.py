# Run inside the QGIS desktop (qgis --code THIS), started by tests/test_desktop.py under Xvfb.
# For every sylva algorithm, as a user would: open its dialog with only the required inputs, read back every
# widget's value, check the algorithm accepts them (checkParameterValues), take a screenshot, press Run (the
# dialog's own runAlgorithm), wait for it to finish and record the layers it added to the project; finally a
# screenshot of the main window with the loaded layers. Writes JSON to $SYLVA_DESKTOP_REPORT and PNGs to
# $SYLVA_DESKTOP_ARTEFACTS. The inputs come as JSON in $SYLVA_DESKTOP_INPUTS: {algorithm id: {param: value}}.
import json
import os
import time
import traceback

from qgis.core import QgsApplication, QgsProject
from qgis.PyQt.QtCore import QObject, QTimer, QUrl, pyqtSlot
from qgis.PyQt.QtGui import QDesktopServices
from qgis.PyQt.QtWidgets import QApplication, QDialogButtonBox
from qgis.utils import iface

REPORT = os.environ["SYLVA_DESKTOP_REPORT"]
ART = os.environ["SYLVA_DESKTOP_ARTEFACTS"]
INPUTS = json.loads(os.environ["SYLVA_DESKTOP_INPUTS"])
TIMEOUT_S = float(os.environ.get("SYLVA_DESKTOP_TIMEOUT", "120"))
report = {"algorithms": {}, "error": None, "qgis": None, "interpreter": None, "project_layers": []}
queue = []


class OpenedUrls(QObject):
    """Catches the file:// URLs the desktop would hand to a browser (the dialogs' Help button)."""

    def __init__(self):
        super().__init__()
        self.urls = []

    @pyqtSlot(QUrl)
    def open(self, url):
        self.urls.append(url.toString())


OPENED = OpenedUrls()
QDesktopServices.setUrlHandler("file", OPENED, "open")


def save(name, widget):
    path = os.path.join(ART, name)
    widget.grab().save(path)
    return path


def finish():
    try:
        layers = list(QgsProject.instance().mapLayers().values())
        report["project_layers"] = [[layer.name(), layer.type(), layer.isValid()] for layer in layers]
        props = getattr(QgsProject.instance(), "elevationProperties", None)   # QGIS >= 3.26: the project terrain
        if props is not None:
            terrain = props().terrainProvider()
            dem = terrain.layer() if hasattr(terrain, "layer") else None
            report["terrain"] = [terrain.type(), dem.name() if dem is not None else None]
        canvas = iface.mapCanvas()
        root = QgsProject.instance().layerTreeRoot()
        for layer in layers:   # the 2D map of the results: crowns and tops over nothing else
            node = root.findLayer(layer.id())
            if node is not None:
                node.setItemVisibilityChecked(layer.name().startswith(("Crowns", "Tree tops")))
        crowns = [layer for layer in layers if layer.name().lower().startswith("crowns")]
        if crowns:
            canvas.setDestinationCrs(crowns[0].crs())
            canvas.setExtent(canvas.mapSettings().layerExtentToOutputExtent(crowns[0], crowns[0].extent()))
        else:
            canvas.zoomToFullExtent()
        canvas.refreshAllLayers()
        tables = [layer for layer in layers if layer.name() == "Trees table" and layer.featureCount() > 100]
        if tables:   # the trees table as a user opens it: values rounded, not nine decimals
            feature = next(tables[0].getFeatures())
            report["trees_row"] = {f.name(): feature[f.name()] for f in tables[0].fields()}
            table = iface.showAttributeTable(tables[0])
            table.resize(1400, 500)
            QTimer.singleShot(1500, lambda: (save("trees_table.png", table), table.close()))
        QTimer.singleShot(4000, final_shot)
    except Exception:
        report["error"] = traceback.format_exc()[-1500:]
        write_and_exit()


def final_shot():
    try:
        report["main_window"] = save("main_window.png", iface.mainWindow())
    except Exception:
        report["error"] = traceback.format_exc()[-1500:]
    write_and_exit()


def write_and_exit():
    with open(REPORT, "w") as f:
        json.dump(report, f, indent=1, default=str)
    QgsApplication.exit(0)


def next_algorithm():
    if not queue:
        finish()
        return
    aid = queue.pop(0)
    entry = report["algorithms"].setdefault(aid, {})
    try:
        run_dialog(aid, entry)
    except Exception:
        entry["error"] = traceback.format_exc()[-1500:]
        QTimer.singleShot(0, next_algorithm)


def run_dialog(aid, entry):
    import processing

    alg = QgsApplication.processingRegistry().algorithmById(aid)
    given = INPUTS.get(aid, {})
    dlg = processing.createAlgorithmDialog(aid, given)
    dlg.show()
    dlg.resize(1000, 900)
    QApplication.processEvents()
    widgets, refused = {}, []
    for name, wrapper in dlg.mainWidget().wrappers.items():
        try:
            value = wrapper.parameterValue()
        except Exception as exc:  # a widget that cannot give its value
            value = f"ERROR {exc}"
        widgets[name] = str(value)
        pdef = alg.parameterDefinition(name)
        if pdef is not None and pdef.defaultValue() is not None and not pdef.checkValueIsAcceptable(value):
            refused.append(name)
    entry["widgets"] = widgets
    entry["refused_widgets"] = refused
    entry["help_url"] = alg.helpUrl()
    entry["outputs_declared"] = [o.name() for o in alg.outputDefinitions()]
    parameters = dlg.createProcessingParameters()   # what Run reads from the widgets
    context = dlg.processingContext() if hasattr(dlg, "processingContext") else None
    if context is None:
        from processing.tools import dataobjects

        context = dataobjects.createContext()
    ok, message = alg.checkParameterValues(parameters, context)
    entry["accepted"] = bool(ok)
    entry["check_message"] = message
    entry["dialog_png"] = save(f"{aid.split(':')[1]}_dialog.png", dlg)
    # the Help button, as a user presses it: what it opens
    seen = len(OPENED.urls)
    helps = [b.button(QDialogButtonBox.Help) for b in dlg.findChildren(QDialogButtonBox)]
    helps = [b for b in helps if b is not None and b.isVisible()]
    if helps:
        helps[0].click()
        QApplication.processEvents()
    entry["help_buttons"] = len(helps)
    entry["help_opened"] = OPENED.urls[seen:]
    before = set(QgsProject.instance().mapLayers())
    if not ok:
        dlg.close()
        QTimer.singleShot(0, next_algorithm)
        return
    started = time.time()
    state = {"done": False}

    def finished(successful, results):
        if state["done"]:
            return
        state["done"] = True
        entry["successful"] = bool(successful)
        entry["seconds"] = round(time.time() - started, 1)
        entry["results"] = {k: str(v) for k, v in (results or {}).items()}
        QTimer.singleShot(500, lambda: after_run(aid, entry, dlg, before))

    dlg.algorithmFinished.connect(finished)

    def watchdog():
        if not state["done"]:
            if time.time() - started > TIMEOUT_S:
                state["done"] = True
                entry["successful"] = False
                entry["error"] = f"no result after {TIMEOUT_S} s"
                after_run(aid, entry, dlg, before)
            else:
                QTimer.singleShot(500, watchdog)

    dlg.runAlgorithm()       # what the Run button does
    QTimer.singleShot(500, watchdog)


def after_run(aid, entry, dlg, before):
    try:
        added = [QgsProject.instance().mapLayer(i) for i in set(QgsProject.instance().mapLayers()) - before]
        entry["layers"] = sorted([layer.name(), layer.isValid(), layer.featureCount() if hasattr(layer, "featureCount")
                                  else -1] for layer in added if layer is not None)
        entry["log_png"] = save(f"{aid.split(':')[1]}_log.png", dlg)
        entry["log_tail"] = dlg.textLog.toPlainText()[-1500:] if hasattr(dlg, "textLog") else ""
    except Exception:
        entry["error"] = traceback.format_exc()[-1500:]
    dlg.close()
    QTimer.singleShot(0, next_algorithm)


def start():
    try:
        from processing.core.ProcessingConfig import ProcessingConfig

        from sylva.plugin import deps

        from qgis.core import Qgis

        report["qgis"] = Qgis.QGIS_VERSION
        report["interpreter"] = deps.interpreter()
        # Keep the dialog open after a run (to take a screenshot of its log), and do not stop on the CRS
        # question the drawings of treefromsketch (no CRS) against its location raise.
        ProcessingConfig.setSettingValue(ProcessingConfig.KEEP_DIALOG_OPEN, True)
        ProcessingConfig.setSettingValue(ProcessingConfig.WARN_UNMATCHING_CRS, False)
        provider = QgsApplication.processingRegistry().providerById("sylva")
        if provider is None:
            report["error"] = "no sylva provider in the Processing registry"
            write_and_exit()
            return
        order = os.environ.get("SYLVA_DESKTOP_ORDER", "")
        ids = [a.id() for a in provider.algorithms()]
        queue.extend([i for i in order.split(",") if i in ids] + [i for i in ids if i not in order.split(",")])
        report["order"] = list(queue)
        next_algorithm()
    except Exception:
        report["error"] = traceback.format_exc()[-1500:]
        write_and_exit()


QTimer.singleShot(2000, start)
