"""Input tiles of a run: LAS/LAZ files, folders of them and QGIS virtual point clouds (``.vpc``).

A ``.vpc`` is a STAC ItemCollection whose features give ``assets.data.href`` and
``proj:bbox``/``bbox`` (QGIS 3.32+ and PDAL wrench write them).  Tiles are read by their headers only.
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Sequence

from ..atomic import atomic_write_bytes
from ..errors import CRSError, InputError, SylvaError

LAS_SUFFIXES = (".las", ".laz")


@dataclass(frozen=True)
class Tile:
    """One input tile: its path, a unique name, and its (xmin, ymin, xmax, ymax) in CRS units."""

    path: str
    name: str
    bounds: tuple
    points: int = -1
    metres_per_unit: float = 1.0


def read_vpc(path) -> List[tuple]:
    """(file path, bounds or None) of every feature of a QGIS virtual point cloud (.vpc)."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text("utf-8"))
    except (OSError, ValueError) as err:
        raise InputError(f"{path}: not a readable virtual point cloud ({err})") from None
    if doc.get("type") != "FeatureCollection" or not isinstance(doc.get("features"), list):
        raise InputError(f"{path}: not a virtual point cloud (a STAC FeatureCollection with features)")
    out = []
    for i, feature in enumerate(doc["features"]):
        try:
            href = feature["assets"]["data"]["href"]
        except (KeyError, TypeError):
            raise InputError(f"{path}: feature {i} has no assets.data.href") from None
        p = Path(href[7:] if href.startswith("file://") else href)
        p = p if p.is_absolute() else (path.parent / p)
        props = feature.get("properties") or {}
        bbox = props.get("proj:bbox") or feature.get("bbox")
        bounds = None
        if bbox and len(bbox) in (4, 6):
            b = [float(v) for v in bbox]
            bounds = (b[0], b[1], b[2], b[3]) if len(b) == 4 else (b[0], b[1], b[3], b[4])
        out.append((str(p.resolve()), bounds))
    return out


def write_vpc(path, tiles: Sequence[Tile], crs=None) -> Path:
    """Write a minimal QGIS virtual point cloud listing ``tiles`` (paths relative to the .vpc)."""
    path = Path(path)
    features = []
    epsg = crs.to_epsg() if crs is not None and hasattr(crs, "to_epsg") else None
    for t in tiles:
        xmin, ymin, xmax, ymax = t.bounds
        props = {"datetime": "2024-01-01T00:00:00Z", "pc:count": int(t.points), "proj:bbox": [xmin, ymin, xmax, ymax]}
        if epsg:
            props["proj:epsg"] = epsg
        features.append({
            "type": "Feature", "stac_version": "1.0.0",
            "stac_extensions": ["https://stac-extensions.github.io/pointcloud/v1.0.0/schema.json",
                                "https://stac-extensions.github.io/projection/v1.1.0/schema.json"],
            "id": t.name, "geometry": None, "bbox": [xmin, ymin, xmax, ymax], "properties": props,
            "links": [], "assets": {"data": {"href": "./" + os.path.relpath(t.path, path.parent),
                                             "roles": ["data"]}},
        })
    doc = {"type": "FeatureCollection", "features": features}
    return atomic_write_bytes(path, (json.dumps(doc, indent=1) + "\n").encode("utf-8"))


def list_tiles(inputs, crs=None) -> tuple:
    """(tiles, failures): every LAS/LAZ of ``inputs`` (files, folders, .vpc) with its bounds.

    A file whose header cannot be read is a failure (path, reason), not an error.
    Tiles are sorted by path; names are the file stems, made unique.
    """
    from .las import las_info

    if isinstance(inputs, (str, os.PathLike)):
        inputs = [inputs]
    found = {}
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            for f in sorted(p.iterdir()):
                if f.suffix.lower() in LAS_SUFFIXES and f.is_file():
                    found[str(f.resolve())] = None
        elif p.suffix.lower() == ".vpc":
            for f, bounds in read_vpc(p):
                found[f] = bounds
        elif p.suffix.lower() in LAS_SUFFIXES:
            if not p.exists():
                raise InputError(f"{p}: file not found")
            found[str(p.resolve())] = None
        else:
            raise InputError(f"{p}: not a LAS/LAZ file, a folder or a .vpc virtual point cloud")
    if not found:
        raise InputError(f"no LAS/LAZ tiles in {', '.join(map(str, inputs))}")
    tiles, failures, names, infos = [], [], set(), {}
    for path in sorted(found):
        try:
            info = las_info(path, crs=crs)
            b = info.bounds
            bounds = (b[0], b[1], b[3], b[4])
            points = info.point_count
            mpu = float(info.units.horizontal_m)
        except SylvaError as err:
            failures.append({"name": Path(path).stem, "path": path, "status": "failed", "reason": str(err),
                             "attempts": 1})   # a header that cannot be read is not retried
            continue
        infos[path] = info
        name = Path(path).stem
        k = 2
        while name in names:
            name = f"{Path(path).stem}_{k}"
            k += 1
        names.add(name)
        tiles.append(Tile(path, name, bounds, points, mpu))
    if crs is None:
        require_one_crs({t.path: infos[t.path].crs for t in tiles})
    return tiles, failures


def require_one_crs(crs_of: Dict[str, object]) -> None:
    """Refuse tiles in different CRSs (:class:`CRSError` naming the odd ones) — Sylva, not in the papers.

    CRSs are compared as pyproj objects (``equals`` ignoring axis order), not by name: a
    WKT and an EPSG code of one CRS are equal; UTM 12N, UTM 17N and a state plane in feet
    are not.  The largest group of equal CRSs is the run's; tiles without a CRS are odd too
    when others have one.  The CRS parameter reads every tile in one CRS instead.
    """

    groups: List[list] = []   # [crs, [paths]]
    for path, crs in crs_of.items():
        for group in groups:
            a, b = group[0], crs
            if (a is None and b is None) or (a is not None and b is not None
                                             and (a == b or a.equals(b, ignore_axis_order=True))):
                group[1].append(path)
                break
        else:
            groups.append([crs, [path]])
    if len(groups) <= 1:
        return
    groups.sort(key=lambda g: (-len(g[1]), g[0] is None))
    main = groups[0][0]
    odd = "; ".join(f"{Path(p).name} ({'no CRS' if g[0] is None else g[0].name})"
                    for g in groups[1:] for p in g[1])
    raise CRSError(f"the tiles of a run must share one CRS: {len(groups[0][1])} tile(s) are in "
                   f"{'no CRS' if main is None else main.name}, but {odd}; reproject those tiles, or set "
                   "the CRS parameter to read every tile in one CRS")


def file_checksum(path, block: int = 1 << 22) -> str:
    """BLAKE2b (16 bytes) of a file's bytes."""
    h = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as fh:
        while True:
            data = fh.read(block)
            if not data:
                break
            h.update(data)
    return h.hexdigest()
