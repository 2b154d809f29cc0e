"""Parameters and steps that several algorithms share."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

from ..core.errors import CRSError, InputError
from .spec import CRS, ENUM, FILE, INTEGER, LEAF_LABELS, NUMBER, STRING, Feedback, Param

POINT_CLOUD_FILTER = "LAS/LAZ point clouds (*.las *.laz);;Text point clouds (*.xyz *.txt *.csv);;All files (*)"
RASTER_SUFFIXES = (".tif", ".tiff")


def input_cloud(help_extra: str = "") -> Param:
    return Param(
        "INPUT", FILE, "Input point cloud (LAS/LAZ)",
        file_filter=POINT_CLOUD_FILTER,
        help="An airborne LiDAR tile: LAS or LAZ 1.0–1.4 (COPC too), or an x y z text file. "
             "Coordinates in metres or feet are both fine; results keep the tile's CRS." + help_extra,
    )


def min_height_param() -> Param:
    """MIN_HEIGHT_M of every algorithm that finds trees, its default :data:`sylva.core.tops.MIN_TREE_HEIGHT_M`."""
    from ..core.tops import MIN_TREE_HEIGHT_M

    return Param("MIN_HEIGHT_M", NUMBER, "Minimum tree height (m)", default=MIN_TREE_HEIGHT_M, minimum=0.0,
                 maximum=200.0, help="Tops lower than this above the ground are not trees (shrubs, cars, noise); "
                                     "lower points belong to a tree only under its crown.")


def lod_param(advanced: bool = False) -> Param:
    """LOD of every algorithm that builds models, its default :data:`sylva.core.geometry.DEFAULT_LOD`."""
    from ..core.geometry import DEFAULT_LOD

    return Param("LOD", INTEGER, "Level of detail (0–2)", default=DEFAULT_LOD, minimum=0, maximum=2,
                 advanced=advanced,
                 help="0: light models (4-sided branches, twigs under 3 cm pruned; ~40 kB a tree); 1: 8 sides, "
                      "smoothed (~0.5 MB a tree); 2: 12 sides, every twig.")


def top_window_param() -> Param:
    """TOP_WINDOW_M of segmenttrees and pipeline (one chain, core/segment/tile.py): empty, the method's own
    default (e.g. :attr:`sylva.core.segment.NormalizedCut.top_window_m`)."""
    return Param("TOP_WINDOW_M", NUMBER, "Tree-top window (m)", optional=True, minimum=0.0, maximum=50.0,
                 help="Diameter of the local-maximum window that finds the tree tops guiding the "
                      "segmentation; left empty (or 0), each method uses its own measured default.")


def growth_param() -> Param:
    """GROWTH of segmenttrees and pipeline: :data:`sylva.core.segment.ncut.method.GROWTH_PRESETS`."""
    from ..core.segment.ncut.method import GROWTH_PRESETS

    return Param("GROWTH", ENUM, "Trees grown", options=tuple(GROWTH_PRESETS), default="forest", optional=True,
                 labels=("In a forest stand", "In the open (parks, streets, pasture, orchards)"),
                 help="forest (default): crowns as wide as trees grown in a stand (Popescu & Wynne 2004). "
                      "open-grown: trees that grew without neighbours have crowns about 2.5 x as wide, which "
                      "the forest setting cuts into several trees; pick it for park, street and pasture trees "
                      "(normalised cut only; values you set under Advanced parameters are kept).")


def leaves_param(advanced: bool = False, help: str = "auto: needle clusters on conical crowns, leaf cards "
                                                     "(phyllotaxis, Hu §5.6) otherwise; none: bare wood.") -> Param:
    """LEAVES (the leaf kind to grow) of every algorithm that builds models: :data:`sylva.core.forest.LEAVES`."""
    from ..core.forest import LEAVES

    return Param("LEAVES", ENUM, "Leaves", options=LEAVES, default="auto", labels=LEAF_LABELS, advanced=advanced,
                 help=help)


def crs_override() -> Param:
    return Param(
        "CRS", CRS, "Override CRS", optional=True, advanced=True,
        help="Use this CRS instead of the one stored in the file (needed for files without one), "
             "e.g. EPSG:26912.",
    )


def load_cloud(args: dict, feedback: Feedback, require_crs: bool = True):
    """Read INPUT (honouring the CRS override), insisting on a CRS unless ``require_crs`` is False (then a
    file without one is a local engineering frame), and tell the user its units."""
    from ..core.io import read_cloud

    cloud = read_cloud(args["INPUT"], crs=args.get("CRS") or None)
    if cloud.crs is None and require_crs:
        raise CRSError(
            f"{args['INPUT']}: the file has no coordinate reference system; "
            "set the CRS parameter (for example EPSG:32632)"
        )
    frame = (f"CRS {cloud.crs.name}" if cloud.crs is not None else
             "no CRS: a local engineering frame, outputs are written in the file's coordinates")
    feedback.info(f"{Path(args['INPUT']).name}: {len(cloud):,} points, {frame}, units {cloud.units.describe()}")
    return cloud


def is_raster(path: str) -> bool:
    return str(path).lower().endswith(RASTER_SUFFIXES)


def require_existing(path: str) -> str:
    if not path or not Path(path).exists():
        raise InputError(f"{path}: file not found")
    return path


def method_params(cls, texts: dict, advanced: tuple = (), ranges: dict = None, prefix: str = "",
                  optional: tuple = ()) -> tuple:
    """Params for the fields of a method dataclass, named as the fields in upper case.

    ``texts`` maps a field name to (description, help); only those fields are
    exposed, in that order, with the dataclass's own default (one source of
    defaults: the paper's, in the dataclass). ``ranges`` maps every numeric
    field to its (minimum, maximum): the values the dataclass accepts (within
    sane limits), so the front ends refuse the others before the run.
    ``prefix`` starts each label (e.g. "Normalised cut: "), so one method's
    parameters read as a group in the dialog.  ``optional`` fields may be left
    empty (the default then): a field added after a release, so that Modeler
    graphs saved before it, which have no value for it, still validate.
    """
    import dataclasses

    from .spec import BOOLEAN, INTEGER, NUMBER

    ranges = ranges or {}
    defaults = {f.name: f.default for f in dataclasses.fields(cls)}
    params = []
    for field, (description, text) in texts.items():
        default = defaults[field]
        kind = BOOLEAN if isinstance(default, bool) else INTEGER if isinstance(default, int) else NUMBER
        lo, hi = ranges.get(field, (None, None)) if kind != BOOLEAN else (None, None)
        params.append(Param(field.upper(), kind, prefix + description, default=default,
                            minimum=lo, maximum=hi, help=text, advanced=field in advanced,
                            optional=field in optional))
    return tuple(params)


def build_method(cls, args: dict, **fixed):
    """An instance of ``cls`` from the upper-case args of its exposed fields (see method_params).

    A combination the dataclass refuses (its ValueError) becomes an InputError: one line, no traceback."""
    import dataclasses

    values = {f.name: args[f.name.upper()] for f in dataclasses.fields(cls)
              if args.get(f.name.upper()) is not None}  # an optional value left empty keeps the default
    values.update(fixed)
    try:
        return cls(**values)
    except ValueError as exc:
        raise InputError(f"parameters: {exc}") from None


def drop_noise(cloud, feedback: Feedback):
    """(cloud without noise points, boolean mask of the kept points); tells the user how many."""
    from ..core.noise import noise_mask

    noise = noise_mask(cloud)
    if noise.any():
        feedback.info(f"{int(noise.sum()):,} noise points left out (classes 7/18, withheld, isolated)")
    keep = ~noise
    return cloud.subset(keep), keep


def load_segmented(args: dict, feedback: Feedback):
    """(cloud without noise, with ``height`` above ground; its int64 treeID labels) of a segmented INPUT."""
    from ..core.terrain import normalize

    source = load_cloud(args, feedback)
    if "treeID" not in source.attrs:
        raise InputError(f"{args['INPUT']}: the point cloud has no treeID dimension; "
                         "run 'Segment trees' (sylva:segmenttrees) on it first")
    cloud, _ = drop_noise(source, feedback)
    if cloud.attr("height") is None:
        feedback.progress(0.02, "height above ground")
        cloud = normalize(cloud)
    from ..core.io.las import tree_labels

    labels = tree_labels(cloud.attrs["treeID"])
    if not (labels > 0).any():
        raise InputError(f"{args['INPUT']}: no point has a treeID above 0: there is no tree to model")
    return cloud, labels


# --------------------------------------------------------------------------- output paths
# (Sylva, not in the papers.) Checked once, before any computation, by both front ends
# (cli.main and processing.algorithm.SylvaAlgorithm.processAlgorithm): an output may never
# equal, hold or lie inside an input, and its extension must name the format written.

def _suffixes(p) -> tuple:
    """The extensions an output parameter may have (lower case, with the dot); () = any."""
    from . import spec as S

    if p.kind == S.RASTER_OUT:
        return (".tif", ".tiff")
    if p.kind == S.FILE_OUT:
        import re

        found = tuple(dict.fromkeys("." + e.lower() for e in re.findall(r"\*\.([A-Za-z0-9]+)", p.file_filter)))
        return found
    return ()


def _real(path: str) -> Path:
    import os

    return Path(os.path.realpath(os.path.expanduser(str(path).split("|", 1)[0])))


def _input_paths(alg, args: dict, raw: dict) -> list:
    """(parameter name, real path) of every input file or folder of a run."""
    from . import spec as S

    out = []
    for p in alg.inputs:
        value = raw.get(p.name) if p.kind == S.VECTOR else args.get(p.name)
        if p.kind not in (S.FILE, S.RASTER, S.VECTOR) or not value or not isinstance(value, (str, Path)):
            continue
        items = [str(value)]
        if not Path(str(value)).exists() and ";" in str(value):
            items = [v.strip() for v in str(value).split(";") if v.strip()]   # pipeline: several tiles
        for item in items:
            real = _real(item)
            out.append((p.name, real))
            if real.suffix.lower() == ".vpc" and real.is_file():
                from ..core.io.tiles import read_vpc

                try:
                    out.extend((p.name, _real(f)) for f, _ in read_vpc(real))
                except InputError:
                    pass  # the run itself says what is wrong with the .vpc
    return out


def _related(a: Path, b: Path) -> str:
    """'' or how two real paths clash: 'is', 'contains' (a holds b) or 'is inside' (a lies in b)."""
    import os

    if a == b or (a.exists() and b.exists() and os.path.samefile(a, b)):
        return "is"
    if b.is_relative_to(a) if hasattr(b, "is_relative_to") else str(b).startswith(str(a) + os.sep):
        return "contains"
    if a.is_relative_to(b) if hasattr(a, "is_relative_to") else str(a).startswith(str(b) + os.sep):
        return "is inside"
    return ""


def check_paths(alg, args: dict, raw: Optional[dict] = None, outputs: Optional[dict] = None,
                vector_suffixes: tuple = (".gpkg",)) -> None:
    """Refuse, before any computation, outputs that would destroy an input or have the wrong extension.

    ``args`` are the run's typed values; ``raw`` the front end's strings (for VECTOR inputs,
    whose typed value is a table); ``outputs`` {name: path} overrides the output paths
    (Processing's sinks); ``vector_suffixes`` the extensions of vector outputs (() = any, as
    QGIS's sinks write every OGR format).  Raises :class:`~sylva.core.errors.OutputError`
    naming the parameter and the path.
    """
    import os

    from ..core.errors import OutputError
    from . import spec as S

    raw = raw or {}
    targets = []
    for p in alg.outputs:
        value = (outputs or {}).get(p.name, args.get(p.name))
        if not value or not isinstance(value, (str, Path)) or str(value).startswith(("memory:", "TEMPORARY_OUTPUT")):
            continue
        targets.append((p, str(value)))
    inputs = _input_paths(alg, args, raw)
    seen = {}
    for p, value in targets:
        path = _real(value)
        shown = str(value).split("|", 1)[0]
        for name, src in inputs:
            how = _related(path, src)
            if how:
                what = {"is": "is the input", "contains": "holds the input", "is inside": "lies inside the input"}[how]
                raise OutputError(f"--{p.name}={shown}: the output {what} --{name}={src}; it would be "
                                  "overwritten or mixed with the results: choose another path")
        suffix = path.suffix.lower()
        if p.kind == S.FOLDER_OUT:
            if path.exists() and not path.is_dir():
                raise OutputError(f"--{p.name}={shown}: is a file, not a folder")
        else:
            allowed = vector_suffixes if p.kind == S.VECTOR_OUT else _suffixes(p)
            if allowed and suffix not in allowed:
                raise OutputError(f"--{p.name}={shown}: {p.description} is written as "
                                  f"{' or '.join(allowed)}; the name ends in {suffix or 'no extension'}")
            if path.is_dir():
                raise OutputError(f"--{p.name}={shown}: is a folder, not a file name")
        parent = path if p.kind == S.FOLDER_OUT else path.parent
        while not parent.exists() and parent != parent.parent:
            parent = parent.parent   # a folder output is created with its parents
        if p.kind != S.FOLDER_OUT and not path.parent.is_dir():
            raise OutputError(f"--{p.name}={shown}: the folder {path.parent} does not exist")
        if not parent.is_dir():
            raise OutputError(f"--{p.name}={shown}: {parent} is a file, not a folder")
        if not os.access(parent, os.W_OK | os.X_OK) or _read_only(parent):
            raise OutputError(f"--{p.name}={shown}: the folder {parent} is not writable")
        for other, (q, other_path) in seen.items():
            if p.kind == S.VECTOR_OUT and q.kind == S.VECTOR_OUT:
                continue   # several layers may share one GeoPackage
            how = _related(path, other_path)
            if how:
                raise OutputError(f"--{p.name}={shown} and --{q.name}: two outputs cannot share a path "
                                  "(or lie in one another's folder)")
        seen[p.name] = (p, path)


def _read_only(folder: Path) -> bool:
    """True on a read-only mount (root passes os.access on read-only permissions, not on ro mounts)."""
    import os

    try:
        return bool(os.statvfs(folder).f_flag & os.ST_RDONLY)
    except (OSError, AttributeError):
        return False


class OutputGuard:
    """Snapshot of a run's output paths; :meth:`rollback` removes what a failed run wrote there.

    A file output that the run created or replaced is removed; a folder output that did
    not exist is removed with its contents; in a folder that existed, the entries the run
    created or changed are removed (a full disk must not leave 6 of 222 GLBs behind).
    ``OUTPUT_FOLDER`` (the pipeline's folder) is left alone: its parts are what RESUME reuses,
    and the catalog cleans its own temporary files (Sylva, not in the papers).
    """

    def __init__(self, alg, args: dict, outputs: Optional[dict] = None):
        from . import spec as S

        self.entries = []
        for p in alg.outputs:
            value = (outputs or {}).get(p.name, args.get(p.name))
            if not value or not isinstance(value, (str, Path)) or p.name == "OUTPUT_FOLDER":
                continue
            path = Path(str(value).split("|", 1)[0])
            if str(path).startswith(("memory:", "TEMPORARY_OUTPUT")):
                continue
            if "|" in str(value) and path.exists():
                continue   # a layer written into an existing GeoPackage: its other layers are not ours to remove
            folder = p.kind == S.FOLDER_OUT
            if folder:
                children = {c.name: self._stat(c) for c in path.iterdir()} if path.is_dir() else None
            else:   # its side files (.prj, .origin.json, .mtl, textures) are named after it
                children = {c.name: self._stat(c) for c in self._siblings(path)}
            self.entries.append((path, folder, self._stat(path), children))

    @staticmethod
    def _siblings(path: Path) -> list:
        """Files beside ``path`` named after it (``stem.*``, ``stem_*`` with spaces as ``_``), but not itself."""
        if not path.parent.is_dir():
            return []
        stems = {path.stem, "_".join(path.stem.split())}
        return [c for c in path.parent.iterdir() if c != path and c.is_file()
                and any(c.name.startswith((f"{s}.", f"{s}_")) for s in stems)]

    @staticmethod
    def _stat(path: Path):
        try:
            st = path.stat()
        except OSError:
            return None
        return (st.st_ino, st.st_mtime_ns, st.st_size)

    def describe(self) -> str:
        """The output paths, for a message that has no file name of its own."""
        return ", ".join(str(path) for path, _, _, _ in self.entries) or "the outputs"

    def rollback(self) -> None:
        import shutil

        for path, folder, before, children in self.entries:
            try:
                if not folder:
                    if path.is_file() and self._stat(path) != before:
                        path.unlink()
                    for side in path.parent.glob(f".{path.name}.*.part"):
                        side.unlink(missing_ok=True)
                    for side in self._siblings(path):
                        if side.name not in children or children[side.name] != self._stat(side):
                            side.unlink(missing_ok=True)
                elif before is None:
                    shutil.rmtree(path, ignore_errors=True)
                elif path.is_dir():
                    for child in path.iterdir():
                        if children.get(child.name) is None or (child.is_file() and children[child.name] != self._stat(child)):
                            shutil.rmtree(child, ignore_errors=True) if child.is_dir() else child.unlink(missing_ok=True)
            except OSError:
                pass


# --------------------------------------------------------------------------- runs over tiles

def tiles_input() -> Param:
    """INPUT of the algorithms that run over a survey's tiles (each with its neighbours' buffer)."""
    return Param("INPUT", FILE, "Tiles (.vpc, LAS/LAZ or folder)",
                 file_filter="Virtual point clouds (*.vpc);;LAS/LAZ (*.las *.laz);;All files (*)",
                 help="A QGIS virtual point cloud (.vpc), one LAS/LAZ file, or a folder of LAS/LAZ tiles; "
                      "several separated by ';'.")


def buffer_param() -> Param:
    return Param("BUFFER_M", NUMBER, "Neighbour buffer (m)", default=15.0, minimum=0.0, maximum=200.0,
                 help="Width of the ring of neighbouring points read around each tile; wider than the "
                      "widest crown.")


def workers_param() -> Param:
    return Param("WORKERS", INTEGER, "Parallel workers (processes)", default=1, minimum=1, maximum=256,
                 help="Local processes working on tiles at once (each needs the memory of one tile and "
                      "its buffer).")


def scheduler_param() -> Param:
    return Param("SCHEDULER", STRING, "Dask scheduler address", optional=True, advanced=True,
                 help="e.g. tcp://10.0.0.5:8786 (tcp:// or tls:// only): send the tiles to a dask.distributed "
                      "cluster instead of local workers (needs 'pip install dask[distributed]'; workers must see "
                      "the same paths). A scheduler is trusted code execution: dask exchanges tasks and results "
                      "pickled, so a scheduler or worker you do not control can run any code on this machine; "
                      "never take this address from a project file you did not write.")


def scheduler_of(args: dict):
    """The SCHEDULER address, or None for local workers."""
    return (args.get("SCHEDULER") or "").strip() or None


def tiles_and_folder(args: dict):
    """(the INPUT paths, separated by ';'; OUTPUT_FOLDER created if missing), or one line naming what is wrong."""
    from ..core.errors import disk_error

    inputs = [p.strip() for p in str(args.get("INPUT") or "").split(";") if p.strip()]
    if not inputs:
        raise InputError("INPUT: give a .vpc virtual point cloud, a folder of LAS/LAZ tiles or LAS/LAZ files")
    out = args.get("OUTPUT_FOLDER")
    if not out:
        raise InputError("OUTPUT_FOLDER: choose an output folder")
    if Path(out).exists() and not Path(out).is_dir():
        raise InputError(f"OUTPUT_FOLDER={out}: is a file, not a folder")
    try:
        Path(out).mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise disk_error(out, err) from None
    return inputs, out
