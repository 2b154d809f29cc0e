"""One QgsProcessingAlgorithm class that runs any sylva.algorithms definition.

Each :class:`~sylva.algorithms.spec.Param` becomes the matching Processing
parameter; ``processAlgorithm`` reads the values, runs the shared ``run``
function with QGIS's feedback wired to progress and cancel, turns
SylvaErrors into QgsProcessingException (a message, not a traceback) and
writes vector results through feature sinks, so outputs work as files,
temporary layers and Graphical Modeler links alike.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

from qgis.core import (
    QgsCoordinateReferenceSystem,
    QgsFeature,
    QgsFeatureSink,
    QgsField,
    QgsFields,
    QgsGeometry,
    QgsProcessing,
    QgsProcessingAlgorithm,
    QgsProcessingException,
    QgsProcessingOutputNumber,
    QgsProcessingOutputString,
    QgsProcessingParameterBoolean,
    QgsProcessingParameterCrs,
    QgsProcessingParameterDefinition,
    QgsProcessingParameterEnum,
    QgsProcessingParameterFeatureSink,
    QgsProcessingParameterFeatureSource,
    QgsProcessingParameterFile,
    QgsProcessingParameterFileDestination,
    QgsProcessingParameterFolderDestination,
    QgsProcessingParameterNumber,
    QgsProcessingParameterRasterDestination,
    QgsProcessingParameterRasterLayer,
    QgsProcessingParameterString,
    QgsWkbTypes,
)
from qgis.PyQt.QtCore import QUrl, QVariant

from ..algorithms import spec as S
from ..core.errors import SylvaError
from ..plugin import deps

#: The HTML help page of each algorithm (resources/help/ID.html, made by sylva.algorithms.helppages).
HELP = Path(__file__).resolve().parents[1] / "resources" / "help"

_SINK_TYPES = {S.POINT: QgsProcessing.TypeVectorPoint, S.LINE: QgsProcessing.TypeVectorLine,
               S.POLYGON: QgsProcessing.TypeVectorPolygon, S.NO_GEOMETRY: QgsProcessing.TypeVector}
_WKB = {("line", "zm"): QgsWkbTypes.MultiLineStringZM,
        ("point", True): QgsWkbTypes.PointZ, ("point", False): QgsWkbTypes.Point,
        ("line", True): QgsWkbTypes.MultiLineStringZ, ("line", False): QgsWkbTypes.MultiLineString,
        ("polygon", True): QgsWkbTypes.MultiPolygonZ, ("polygon", False): QgsWkbTypes.MultiPolygon,
        ("none", True): QgsWkbTypes.NoGeometry, ("none", False): QgsWkbTypes.NoGeometry}
_QVARIANT = {"integer": QVariant.LongLong, "real": QVariant.Double, "text": QVariant.String}

#: pyproj's per-thread PROJ contexts, kept alive by OS thread (see keep_pyproj_context)
_PYPROJ_CONTEXTS: dict = {}


def keep_pyproj_context() -> None:
    """Keep this OS thread's pyproj PROJ context alive after the algorithm returns.

    pyproj >= 3.5 (Debian 13's 3.7) caches one PROJ context per OS thread (a pthread key) but owns it
    through a ``threading.local``, which dies with the Python thread state. QGIS runs an algorithm in
    a pooled QThread that enters Python with a fresh thread state each time, so after one run the
    context was destroyed while the key still pointed to it, and the next run in the same thread
    crashed QGIS 3.40 inside PROJ (``projCppContext::getDatabaseContext``, signal 11). Holding the
    context's owner here, one per pool thread, keeps the pointer valid (a thread id reused by a new
    thread replaces, and so frees, the dead thread's context). Older pyproj: nothing to do.
    """
    try:
        import threading

        from pyproj._context import get_context_manager
    except ImportError:
        return
    try:
        manager = get_context_manager()
    except Exception:  # noqa: BLE001 — a pyproj without it
        return
    if manager is not None:
        _PYPROJ_CONTEXTS[threading.get_native_id()] = manager


class QgisFeedback(S.Feedback):
    def __init__(self, feedback):
        self.feedback = feedback
        self._step = -1

    def progress(self, fraction, message=""):
        step = int(fraction * 20)  # a progress text every 5 % at most: logs stay readable
        if message and step != self._step:
            self._step = step
            self.feedback.setProgressText(message)
        self.feedback.setProgress(100.0 * fraction)

    def cancelled(self):
        return self.feedback.isCanceled()

    def info(self, message):
        self.feedback.pushInfo(message)

    def warn(self, message):
        self.feedback.pushWarning(message)   # orange in the dialog's log, "WARNING:" from qgis_process


def qgs_parameter(p: S.Param):
    """The QgsProcessingParameterDefinition for a Sylva Param."""
    k = p.kind
    if k == S.FILE:
        q = QgsProcessingParameterFile(p.name, p.description, QgsProcessingParameterFile.File,
                                       fileFilter=p.file_filter, optional=p.optional)
    elif k in (S.NUMBER, S.INTEGER):
        q = QgsProcessingParameterNumber(
            p.name, p.description,
            QgsProcessingParameterNumber.Double if k == S.NUMBER else QgsProcessingParameterNumber.Integer,
            p.default, p.optional, p.minimum, p.maximum)  # finite bounds, within 32 bits for integers (spec.Param)
    elif k == S.BOOLEAN:
        q = QgsProcessingParameterBoolean(p.name, p.description, bool(p.default), p.optional)
    elif k == S.ENUM:
        q = QgsProcessingParameterEnum(p.name, p.description, list(p.option_labels), False,
                                       p.options.index(p.default) if p.default else None, p.optional)
    elif k == S.CRS:
        q = QgsProcessingParameterCrs(p.name, p.description, p.default, True)
    elif k == S.STRING:
        q = QgsProcessingParameterString(p.name, p.description, p.default, False, p.optional)
    elif k == S.RASTER:
        q = QgsProcessingParameterRasterLayer(p.name, p.description, None, p.optional)
    elif k == S.VECTOR:
        q = QgsProcessingParameterFeatureSource(p.name, p.description, [_SINK_TYPES[p.geometry]], None, p.optional)
    elif k == S.RASTER_OUT:
        q = QgsProcessingParameterRasterDestination(p.name, p.description, None, p.optional)
    elif k == S.VECTOR_OUT:
        q = QgsProcessingParameterFeatureSink(p.name, p.description, _SINK_TYPES[p.geometry], None, p.optional)
    elif k == S.FILE_OUT:
        q = QgsProcessingParameterFileDestination(p.name, p.description, p.file_filter, None, p.optional)
    elif k == S.FOLDER_OUT:
        q = QgsProcessingParameterFolderDestination(p.name, p.description, None, p.optional)
    else:  # pragma: no cover - a new kind must be mapped here
        raise ValueError(f"no Processing parameter for kind {k!r}")
    q.setHelp(p.help + S.param_facts(p))
    if k == S.NUMBER:   # the spin box shows the decimals the values need (2.0, 0.05), not always six
        q.setMetadata({"widget_wrapper": {"decimals": _decimals(p)}})
    if p.advanced:
        q.setFlags(q.flags() | QgsProcessingParameterDefinition.FlagAdvanced)
    return q


def _decimals(p: S.Param) -> int:
    """Decimals a number's spin box needs to show its default and its bounds exactly (1 to 6)."""
    def places(v):
        text = f"{float(v):.6f}".rstrip("0")
        return len(text.split(".")[1]) if "." in text else 0

    return max([1] + [places(v) for v in (p.default, p.minimum, p.maximum) if v is not None])


def to_qgs_crs(crs) -> QgsCoordinateReferenceSystem:
    if crs is None:
        return QgsCoordinateReferenceSystem()
    epsg = crs.to_epsg()
    if epsg:
        return QgsCoordinateReferenceSystem(f"EPSG:{epsg}")
    return QgsCoordinateReferenceSystem.fromWkt(crs.to_wkt())


def vector_table(source, p: S.Param):
    """A QgsFeatureSource as a core VectorTable (shapely geometries, attribute columns, pyproj CRS)."""
    import numpy as np
    import pyproj
    import shapely

    names = [f.name() for f in source.fields()]
    geoms, rows = [], []
    for feature in source.getFeatures():
        g = feature.geometry()
        if g is None or g.isNull():
            geoms.append(None)
        else:
            g = QgsGeometry(g.constGet().clone())
            g.get().dropMValue()  # shapely has no M
            geoms.append(shapely.from_wkb(bytes(g.asWkb())))
        rows.append([None if v is None or (hasattr(v, "isNull") and v.isNull()) else v
                     for v in feature.attributes()])
    columns = {}
    for i, name in enumerate(names):
        vals = [r[i] for r in rows]
        if vals and all(isinstance(v, int) and not isinstance(v, bool) for v in vals):
            columns[name] = np.array(vals, dtype=np.int64)
        elif vals and all(isinstance(v, (int, float)) or v is None for v in vals):
            columns[name] = np.array([np.nan if v is None else float(v) for v in vals])
        else:
            columns[name] = np.array([None if v is None else str(v) for v in vals], dtype=object)
    crs = source.sourceCrs()
    pcrs = pyproj.CRS.from_wkt(crs.toWkt(QgsCoordinateReferenceSystem.WKT_PREFERRED)) if crs.isValid() else None
    gtype = {QgsWkbTypes.PointGeometry: S.POINT, QgsWkbTypes.LineGeometry: S.LINE,
             QgsWkbTypes.PolygonGeometry: S.POLYGON}.get(QgsWkbTypes.geometryType(source.wkbType()), S.NO_GEOMETRY)
    from ..core.table import VectorTable

    return VectorTable(p.name.lower(), gtype, np.array(geoms, dtype=object) if gtype != S.NO_GEOMETRY else None,
                       columns, pcrs, has_z=QgsWkbTypes.hasZ(source.wkbType()))


class SylvaAlgorithm(QgsProcessingAlgorithm):
    def __init__(self, spec: S.Algorithm):
        super().__init__()
        self.spec = spec

    def createInstance(self):  # noqa: N802
        return SylvaAlgorithm(self.spec)

    def name(self):
        return self.spec.id

    def displayName(self):  # noqa: N802
        return self.spec.name

    def group(self):
        return self.spec.group

    def groupId(self):  # noqa: N802
        return self.spec.group_id

    def shortHelpString(self):  # noqa: N802
        from ..algorithms.helppages import short_help

        return short_help(self.spec)

    def helpUrl(self):  # noqa: N802
        page = HELP / f"{self.spec.id}.html"
        return QUrl.fromLocalFile(str(page)).toString() if page.is_file() else ""

    def initAlgorithm(self, config=None):  # noqa: N802
        for p in self.spec.params:
            self.addParameter(qgs_parameter(p))
            for old in p.aliases:
                # an earlier name, hidden and optional: a Modeler graph or script saved with it keeps its
                # value (a graph passes a child only the values of names the algorithm defines)
                q = qgs_parameter(dataclasses.replace(p, name=old, default=None, optional=True, aliases=()))
                q.setFlags(q.flags() | QgsProcessingParameterDefinition.FlagHidden)
                self.addParameter(q)
        for r in self.spec.results:
            cls = QgsProcessingOutputNumber if r.kind == S.NUMBER_RESULT else QgsProcessingOutputString
            self.addOutput(cls(r.name, r.description))

    def _plain(self, parameters):
        """``parameters`` with enum values given as an option id or label turned into the option's index
        (qgis_process and Python callers may pass "ncut" or its label as the CLI does)."""
        out = S.with_aliases(self.spec, parameters)
        for p in self.spec.params:
            value = out.get(p.name)
            if p.kind == S.ENUM and isinstance(value, str) and value.strip() and not value.strip().isdigit():
                try:
                    out[p.name] = p.options.index(p.option(value))
                except ValueError:
                    pass   # left for QGIS to refuse
        return out

    def checkParameterValues(self, parameters, context):  # noqa: N802
        """QGIS's own checks, then every numeric value against its real range (NaN and infinities refused),
        so qgis_process, processing.run and the dialog say the same one line as the CLI."""
        parameters = self._plain(parameters)
        problem = self._range_problem(parameters, context)
        if problem:
            return False, problem
        return super().checkParameterValues(parameters, context)

    def _range_problem(self, parameters, context):
        for p in self.spec.params:
            if p.kind not in (S.NUMBER, S.INTEGER):
                continue
            raw = parameters.get(p.name)
            if raw is None or (isinstance(raw, str) and not raw.strip()):
                continue
            if not isinstance(raw, (int, float, str)):   # a QgsProperty, a model link...: read its value
                raw = self.parameterAsDouble(parameters, p.name, context)
            why = p.problem(raw)
            if why:
                return f"{p.name} ({p.description}): {why}"
        return None

    def _value(self, p: S.Param, parameters, context):
        k = p.kind
        if k == S.FILE:
            return self.parameterAsFile(parameters, p.name, context)
        if k in (S.NUMBER, S.INTEGER) and p.optional and parameters.get(p.name) in (None, ""):
            return None   # an optional number left empty: the method's own default (not 0)
        if k == S.NUMBER:
            return self.parameterAsDouble(parameters, p.name, context)
        if k == S.INTEGER:
            return self.parameterAsInt(parameters, p.name, context)
        if k == S.BOOLEAN:
            return self.parameterAsBoolean(parameters, p.name, context)
        if k == S.ENUM:
            return p.options[self.parameterAsEnum(parameters, p.name, context)]
        if k == S.CRS:
            crs = self.parameterAsCrs(parameters, p.name, context)
            return (crs.authid() or crs.toWkt()) if crs.isValid() else None
        if k == S.STRING:
            return self.parameterAsString(parameters, p.name, context)
        if k == S.RASTER:
            layer = self.parameterAsRasterLayer(parameters, p.name, context)
            return layer.source() if layer is not None else None
        if k == S.VECTOR:
            source = self.parameterAsSource(parameters, p.name, context)
            return vector_table(source, p) if source is not None else None
        if k == S.RASTER_OUT:
            return self.parameterAsOutputLayer(parameters, p.name, context)
        if k in (S.FILE_OUT, S.FOLDER_OUT):
            return self.parameterAsFileOutput(parameters, p.name, context)
        return None  # VECTOR_OUT: written through a sink after run()

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802
        try:
            return self._process(parameters, context, feedback)
        finally:
            keep_pyproj_context()

    def _process(self, parameters, context, feedback):
        lacking = deps.missing()
        if lacking:
            raise QgsProcessingException(deps.install_hint(lacking))
        from ..algorithms.common import OutputGuard, check_paths
        from ..core.errors import disk_error

        parameters = self._plain(parameters)
        problem = self._range_problem(parameters, context)
        if problem:
            raise QgsProcessingException(problem)
        guard = None
        try:
            args = {p.name: self._value(p, parameters, context) for p in self.spec.params}
            # outputs checked before any computation, as the CLI does (one shared check)
            sinks = {p.name: self._sink_path(parameters, p.name, context)
                     for p in self.spec.outputs if p.kind == S.VECTOR_OUT}
            raw = {p.name: self.parameterAsString(parameters, p.name, context)
                   for p in self.spec.inputs if p.kind == S.VECTOR}
            check_paths(self.spec, args, raw=raw, outputs=sinks, vector_suffixes=())
            guard = OutputGuard(self.spec, args)
            result = self.spec.run(args, QgisFeedback(feedback))
        except SylvaError as exc:
            if guard is not None:
                guard.rollback()
            raise QgsProcessingException(" ".join(str(exc).split())) from None
        except OSError as exc:   # a full disk, a read-only folder: one line, nothing half-written
            if guard is not None:
                guard.rollback()
            where = exc.filename or (guard.describe() if guard is not None else "output")
            raise QgsProcessingException(str(disk_error(where, exc))) from None
        except BaseException:
            if guard is not None:
                guard.rollback()
            raise
        outputs = dict(result.files)
        shared = self._shared_geopackages(parameters, context, list(result.vectors))
        for name, table in result.vectors.items():
            params = parameters
            if name in shared:
                params = dict(parameters)
                params[name] = _layer_of(parameters[name], shared[name], table)
            outputs[name] = self._write_sink(params, name, table, context, feedback)
        outputs.update(result.values)
        # -- the run's layers (folder outputs Processing does not load itself), styled: processing/outputs.py
        from .outputs import load_on_completion

        load_on_completion(self.spec.id, result.files, result.values, context)
        return outputs

    def _sink_path(self, parameters, name, context):
        """The file a feature sink will write (None for memory layers and temporary outputs)."""
        try:
            text = _destination(parameters, name)
        except Exception:  # noqa: BLE001 — an unusual destination: QGIS checks it itself
            return None
        if not text or text.startswith(("memory:", "ogr:", "postgres:", "TEMPORARY_OUTPUT")) or "://" in text:
            return None
        return text.split("|", 1)[0]

    def _shared_geopackages(self, parameters, context, names) -> dict:
        """{output: file} for the sinks of this run that name one plain ``.gpkg`` file.

        QGIS lets each such sink overwrite the file (only the last layer stays);
        Sylva makes each its own layer of the file instead, as the CLI does.
        """
        import os

        files = {}
        for name in names:
            dest = _destination(parameters, name)
            if dest.lower().endswith(".gpkg") and "|" not in dest and not dest.startswith("ogr:"):
                files.setdefault(os.path.normcase(os.path.abspath(dest)), []).append(name)
        return {n: path for path, group in files.items() if len(group) > 1 for n in group}

    def _write_sink(self, parameters, name, table, context, feedback):
        fields = QgsFields()
        types = table.field_types()
        for column, kind in types.items():
            fields.append(QgsField(column, _QVARIANT[kind]))
        sink, dest_id = self.parameterAsSink(
            parameters, name, context, fields,
            _WKB[(table.geometry_type, "zm" if table.has_m else table.has_z)], to_qgs_crs(table.crs))
        if sink is None:
            return None
        self._style_on_load(self.spec.param(name).style, dest_id, context)
        import shapely

        from ..core.table import python_values

        wkb = None
        if table.raw:
            wkb = table.geometries  # already ISO WKB
        elif table.geometries is not None:
            wkb = shapely.to_wkb(table.geometries, output_dimension=3 if table.has_z else 2, flavor="iso")
        columns = [python_values(S.display_round(table.columns[c]) if types[c] == "real" else table.columns[c],
                                 types[c]) for c in types]
        n = len(table)
        for i in range(n):
            if i % 10000 == 0 and feedback.isCanceled():
                break
            feature = QgsFeature(fields)
            if wkb is not None and wkb[i] is not None:
                geometry = QgsGeometry()
                geometry.fromWkb(wkb[i])
                feature.setGeometry(_as_multi(geometry, table.geometry_type))
            feature.setAttributes([col[i] for col in columns])
            sink.addFeature(feature, QgsFeatureSink.FastInsert)
        return dest_id

    @staticmethod
    def _style_on_load(style, dest_id, context):
        """Have QGIS apply ``resources/styles/<style>`` when it loads the output at the end of the run."""
        if style and context.willLoadLayerOnCompletion(dest_id):
            from .outputs import StyledOutput

            context.layerToLoadOnCompletionDetails(dest_id).setPostProcessor(StyledOutput.get(style))


def _layer_of(value, path: str, table):
    """The sink ``value`` redirected to layer ``table.name`` of the GeoPackage ``path`` (loading details kept)."""
    from qgis.core import QgsProcessingOutputLayerDefinition, QgsProperty

    quoted = path.replace("\\", "\\\\").replace("'", "\\'")
    geometry = " (geom)" if table.geometry_type != "none" else ""
    uri = f"ogr:dbname='{quoted}' table=\"{table.name}\"{geometry}"
    if isinstance(value, QgsProcessingOutputLayerDefinition):
        value = QgsProcessingOutputLayerDefinition(value)
        value.sink = QgsProperty.fromValue(uri)
        return value
    return uri


def _destination(parameters, name) -> str:
    """The destination text of a sink, read without parameterAsOutputLayer: called from the dialog (whose
    QgsProcessingOutputLayerDefinition asks to load the result), that registers "memory:NAME" as a layer to
    load, which QGIS then reports as "not correctly generated" and the dialog never finishes."""
    from qgis.core import QgsProcessingOutputLayerDefinition, QgsProperty

    value = parameters.get(name)
    if isinstance(value, QgsProcessingOutputLayerDefinition):
        value = value.sink
    if isinstance(value, QgsProperty):
        value = value.staticValue()
    return "" if value is None else str(value)


def _as_multi(geometry, geometry_type):
    if geometry_type in ("line", "polygon") and not geometry.isMultipart():
        geometry.convertToMultiType()
    return geometry



class MissingDependencies(QgsProcessingAlgorithm):
    """Shown instead of Sylva's algorithms when Python packages are missing: says which and how."""

    def __init__(self, lacking):
        super().__init__()
        self.lacking = list(lacking)

    def createInstance(self):  # noqa: N802
        return MissingDependencies(self.lacking)

    def name(self):
        return "dependencies"

    def displayName(self):  # noqa: N802
        return "Install Sylva's Python packages (missing: " + ", ".join(self.lacking) + ")"

    def shortHelpString(self):  # noqa: N802
        return deps.install_hint(self.lacking)

    def initAlgorithm(self, config=None):  # noqa: N802
        pass

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802
        raise QgsProcessingException(deps.install_hint(self.lacking))
