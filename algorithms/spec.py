"""One parameter definition for both front ends.

An :class:`Algorithm` is plain data (id, name, help, :class:`Param` list) plus
a ``run(args, feedback)`` function.  ``processing/`` turns it into a
QgsProcessingAlgorithm and ``cli.py`` into an argparse sub-command, so the
ids, parameter names, defaults and help texts of ``sylva ALGORITHM --PARAM=``
and ``qgis_process run sylva:ALGORITHM --PARAM=`` are the same by
construction.

``run`` receives a dict of plain Python values (paths as str, numbers,
bools, enum values as their option *name*, CRS as a string or None) and
returns a :class:`Result`: vector outputs as :class:`~sylva.core.table.VectorTable`
(each front end writes them its own way: QGIS feature sinks, or GeoPackage
files from the CLI) and file outputs as the paths it wrote.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, Optional, Tuple

# Input kinds
FILE = "file"            # an existing file (point cloud, raster, ...)
NUMBER = "number"        # float
INTEGER = "integer"
BOOLEAN = "boolean"
ENUM = "enum"            # one of `options`; run() receives the option's name
CRS = "crs"              # any string pyproj understands ("EPSG:26912", WKT), optional
STRING = "string"
RASTER = "raster"        # a raster layer; run() receives the path of its file (GeoTIFF)
VECTOR = "vector"        # a vector layer; run() receives a core.table.VectorTable (shapely geometries,
                         # columns, crs) read from the layer, or None when optional and absent;
                         # `geometry` restricts the accepted type (point/line/polygon)
# Output kinds
RASTER_OUT = "raster_out"   # GeoTIFF path
VECTOR_OUT = "vector_out"   # a layer: a feature sink in QGIS, a GeoPackage from the CLI
FILE_OUT = "file_out"       # any other file (LAS/LAZ, GLB, ...)
FOLDER_OUT = "folder_out"

OUTPUT_KINDS = (RASTER_OUT, VECTOR_OUT, FILE_OUT, FOLDER_OUT)

# Kinds of the results an algorithm returns as values (Result.values), declared so that Graphical
# Modeler and qgis_process can use them: QgsProcessingOutputNumber / QgsProcessingOutputString.
NUMBER_RESULT = "number_result"
STRING_RESULT = "string_result"

#: Integer parameters must fit a 32-bit spin box (QGIS 3.22 shows -2147483648 for wider bounds).
INT_MIN, INT_MAX = -2 ** 31, 2 ** 31 - 1

#: Readable labels of the leaf options ("auto", "broadleaf", "needles", "none") wherever they are offered.
LEAF_LABELS = ("Automatic (needles on conical crowns)", "Broadleaf cards", "Needle clusters", "No leaves")

# Geometry kinds of vector outputs (VectorTable.geometry_type uses the same words)
POINT, LINE, POLYGON, NO_GEOMETRY = "point", "line", "polygon", "none"


@dataclass(frozen=True)
class Param:
    name: str
    kind: str
    description: str
    default: Any = None
    optional: bool = False
    minimum: Optional[float] = None
    maximum: Optional[float] = None
    options: Tuple[str, ...] = ()
    file_filter: str = ""          # Qt-style, e.g. "LAS/LAZ (*.las *.laz)"
    geometry: str = POINT           # for VECTOR_OUT and VECTOR
    help: str = ""                  # one or two sentences for the user
    advanced: bool = False
    style: str = ""                 # VECTOR_OUT: a .qml in resources/styles applied when QGIS loads the layer
    labels: Tuple[str, ...] = ()    # ENUM: what the dialog shows for each option (the option ids stay the values)
    aliases: Tuple[str, ...] = ()   # earlier names still accepted (saved Modeler graphs, scripts, batch files)

    def __post_init__(self):
        if self.kind in (NUMBER, INTEGER):
            lo, hi = self.minimum, self.maximum
            if lo is None or hi is None or not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
                raise ValueError(f"{self.name}: a numeric parameter needs a finite range, got [{lo}, {hi}]")
            if self.kind == INTEGER and not (INT_MIN <= lo and hi <= INT_MAX):
                raise ValueError(f"{self.name}: integer bounds must lie within a 32-bit integer")
            if self.default is not None and not lo <= self.default <= hi:
                raise ValueError(f"{self.name}: default {self.default} outside [{lo}, {hi}]")
        if self.kind == ENUM and self.labels and len(self.labels) != len(self.options):
            raise ValueError(f"{self.name}: {len(self.labels)} labels for {len(self.options)} options")

    @property
    def is_output(self) -> bool:
        return self.kind in OUTPUT_KINDS

    @property
    def option_labels(self) -> Tuple[str, ...]:
        """ENUM: the readable label of each option (the option id when no label is given)."""
        return self.labels or self.options

    def option(self, value) -> str:
        """ENUM: the option id for ``value``, which may be the id, its label or its index (int or digits).

        Raises ValueError when it is none of them."""
        if isinstance(value, str):
            text = value.strip()
            if text in self.options:
                return text
            if text in self.option_labels:
                return self.options[self.option_labels.index(text)]
            if not text.lstrip("-").isdigit():
                raise ValueError(value)
            value = int(text)
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < len(self.options):
            raise ValueError(value)
        return self.options[value]

    def problem(self, value) -> Optional[str]:
        """Why ``value`` is not acceptable for this numeric parameter (None when it is).

        Rejects NaN, infinities, non-integers for INTEGER, and values outside [minimum, maximum]:
        the range the core method accepts, so every front end refuses the same values with one line."""
        if self.kind not in (NUMBER, INTEGER) or value is None:
            return None
        try:
            v = float(value)
        except (TypeError, ValueError):
            return f"{value!r} is not a number"
        if not math.isfinite(v):
            return f"{value} is not a finite number"
        if self.kind == INTEGER and v != int(v):
            return f"{value} is not a whole number"
        if not self.minimum <= v <= self.maximum:
            return f"{_fmt(v)} is outside its range [{_fmt(self.minimum)}, {_fmt(self.maximum)}]"
        return None

    def range_text(self) -> str:
        """'0.05 to 10' for the help."""
        return f"{_fmt(self.minimum)} to {_fmt(self.maximum)}" if self.kind in (NUMBER, INTEGER) else ""

    def default_extension(self) -> str:
        if self.kind == RASTER_OUT:
            return ".tif"
        if self.kind == VECTOR_OUT:
            return ".gpkg"
        if self.kind == FILE_OUT and "*." in self.file_filter:
            return "." + self.file_filter.split("*.", 1)[1].split()[0].rstrip(")")
        return ""


def _fmt(v: float) -> str:
    return str(int(v)) if float(v).is_integer() else f"{v:g}"


def display_round(values):
    """Float values rounded to what a table should show: 3 decimals (mm, m², m³, CRS units), and 4 significant
    digits for values under 1 (a 4 mm radius, 0.0004 m³), so attribute tables do not show nine decimals."""
    import numpy as np

    v = np.asarray(values, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        mag = np.floor(np.log10(np.abs(v)))
    decimals = np.where(np.isfinite(mag) & (mag < 0), np.clip(3 - mag, 3, 12), 3).astype(np.int64)
    scale = 10.0 ** decimals
    out = np.round(v * scale) / scale
    return np.where(np.isfinite(v), out, v)


def with_aliases(alg: "Algorithm", values: Dict[str, Any]) -> Dict[str, Any]:
    """``values`` (parameter name -> value) with a value given under an earlier name of a parameter
    (:attr:`Param.aliases`) moved to its current name, unless the current name has a value of its own;
    the earlier names are removed."""
    out = dict(values)
    for p in alg.params:
        for old in p.aliases:
            value = out.pop(old, None)
            if value not in (None, "") and out.get(p.name) in (None, ""):
                out[p.name] = value
    return out


def check_values(alg: "Algorithm", args: Dict[str, Any]) -> None:
    """Raise InputError with one line naming the first numeric parameter of ``args`` out of its range."""
    from ..core.errors import InputError

    for p in alg.params:
        why = p.problem(args.get(p.name))
        if why:
            raise InputError(f"{alg.id}: {p.name} ({p.description}): {why}")


@dataclass
class Result:
    """What ``run`` returns: vector tables to write, and paths already written."""

    vectors: Dict[str, Any] = field(default_factory=dict)   # param name -> VectorTable
    files: Dict[str, str] = field(default_factory=dict)      # param name -> path
    values: Dict[str, Any] = field(default_factory=dict)     # extra outputs (counts, ...)


class Feedback:
    """Progress, cancel and messages, as the core's callbacks expect them.

    The CLI uses this class as it is; the Processing layer subclasses it and
    forwards to QgsProcessingFeedback.
    """

    def progress(self, fraction: float, message: str = "") -> None:  # noqa: D102
        pass

    def cancelled(self) -> bool:  # noqa: D102
        return False

    def info(self, message: str) -> None:  # noqa: D102
        pass

    def warn(self, message: str) -> None:  # noqa: D102
        pass


@dataclass(frozen=True)
class Algorithm:
    id: str
    name: str
    group: str
    summary: str
    params: Tuple[Param, ...]
    run: Callable[[Dict[str, Any], Feedback], Result]
    group_id: str = ""
    results: Tuple[Param, ...] = ()      # NUMBER_RESULT / STRING_RESULT: the values run() returns

    def param(self, name: str) -> Param:
        for p in self.params:
            if p.name == name:
                return p
        raise KeyError(name)

    @property
    def inputs(self) -> Tuple[Param, ...]:
        return tuple(p for p in self.params if not p.is_output)

    @property
    def outputs(self) -> Tuple[Param, ...]:
        return tuple(p for p in self.params if p.is_output)

    def help_text(self) -> str:
        """The long help: the summary, then one paragraph per parameter."""
        lines = [self.summary, ""]
        for p in self.params:
            lines.append(f"{p.name} ({p.description}): {p.help}{param_facts(p)}{alias_text(p)}".rstrip())
        for r in self.results:
            lines.append(f"{r.name} ({r.description}): {r.help}".rstrip())
        return "\n".join(lines)


def alias_text(p: Param) -> str:
    """' Formerly WINDOW_DIAMETER_M (still accepted).' for the help texts."""
    return f" Formerly {', '.join(p.aliases)} (still accepted)." if p.aliases else ""


def param_facts(p: Param) -> str:
    """' Range: 0.05 to 10. Default: 0.7.' and the like, for the help texts."""
    text = ""
    if p.kind == ENUM:
        text += " Options: " + "; ".join(f"{o} ({lab})" if lab != o else o
                                          for o, lab in zip(p.options, p.option_labels)) + "."
    elif p.kind in (NUMBER, INTEGER):
        text += f" Range: {p.range_text()}."
    if p.default is not None and not p.is_output:
        text += f" Default: {p.default}."
    return text
