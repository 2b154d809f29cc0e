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

    @property
    def is_output(self) -> bool:
        return self.kind in OUTPUT_KINDS

    def default_extension(self) -> str:
        if self.kind == RASTER_OUT:
            return ".tif"
        if self.kind == VECTOR_OUT:
            return ".gpkg"
        if self.kind == FILE_OUT and "*." in self.file_filter:
            return "." + self.file_filter.split("*.", 1)[1].split()[0].rstrip(")")
        return ""


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
            default = "" if p.default is None or p.is_output else f" Default: {p.default}."
            if p.kind == ENUM:
                default = f" One of: {', '.join(p.options)}." + (f" Default: {p.default}." if p.default else "")
            lines.append(f"{p.name} ({p.description}): {p.help}{default}".rstrip())
        return "\n".join(lines)
