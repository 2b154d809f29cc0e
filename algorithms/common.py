"""Parameters and steps that several algorithms share."""
from __future__ import annotations

from pathlib import Path

from ..core.errors import CRSError, InputError
from .spec import CRS, FILE, Feedback, Param

POINT_CLOUD_FILTER = "LAS/LAZ point clouds (*.las *.laz);;Text point clouds (*.xyz *.txt *.csv);;All files (*)"
RASTER_SUFFIXES = (".tif", ".tiff")


def input_cloud(help_extra: str = "") -> Param:
    return Param(
        "INPUT", FILE, "Input point cloud (LAS/LAZ)",
        file_filter=POINT_CLOUD_FILTER,
        help="An airborne LiDAR tile: LAS or LAZ 1.0–1.4 (COPC too), or an x y z text file. "
             "Coordinates in metres or feet are both fine; results keep the tile's CRS." + help_extra,
    )


def crs_override() -> Param:
    return Param(
        "CRS", CRS, "Override CRS", optional=True, advanced=True,
        help="Use this CRS instead of the one stored in the file (needed for files without one), "
             "e.g. EPSG:26912.",
    )


def load_cloud(args: dict, feedback: Feedback):
    """Read INPUT (honouring the CRS override), insisting on a CRS, and tell the user its units."""
    from ..core.io import read_cloud

    cloud = read_cloud(args["INPUT"], crs=args.get("CRS") or None)
    if cloud.crs is None:
        raise CRSError(
            f"{args['INPUT']}: the file has no coordinate reference system; "
            "set the CRS parameter (for example EPSG:32632)"
        )
    feedback.info(
        f"{Path(args['INPUT']).name}: {len(cloud):,} points, CRS {cloud.crs.name}, units {cloud.units.describe()}"
    )
    return cloud


def is_raster(path: str) -> bool:
    return str(path).lower().endswith(RASTER_SUFFIXES)


def require_existing(path: str) -> str:
    if not path or not Path(path).exists():
        raise InputError(f"{path}: file not found")
    return path


def method_params(cls, texts: dict, advanced: tuple = (), ranges: dict = None, prefix: str = "") -> tuple:
    """Params for the fields of a method dataclass, named as the fields in upper case.

    ``texts`` maps a field name to (description, help); only those fields are
    exposed, in that order, with the dataclass's own default (one source of
    defaults: the paper's, in the dataclass). ``ranges`` maps every numeric
    field to its (minimum, maximum): the values the dataclass accepts (within
    sane limits), so the front ends refuse the others before the run.
    ``prefix`` starts each label (e.g. "Normalised cut: "), so one method's
    parameters read as a group in the dialog.
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
                            minimum=lo, maximum=hi, help=text, advanced=field in advanced))
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
    import numpy as np

    from ..core.terrain import normalize

    source = load_cloud(args, feedback)
    if "treeID" not in source.attrs:
        raise InputError(f"{args['INPUT']}: the point cloud has no treeID dimension; "
                         "run 'Segment trees' (sylva:segmenttrees) on it first")
    cloud, _ = drop_noise(source, feedback)
    if cloud.attr("height") is None:
        feedback.progress(0.02, "height above ground")
        cloud = normalize(cloud)
    labels = np.asarray(cloud.attrs["treeID"]).astype(np.int64)
    if not (labels > 0).any():
        raise InputError(f"{args['INPUT']}: no point has a treeID above 0: there is no tree to model")
    return cloud, labels
