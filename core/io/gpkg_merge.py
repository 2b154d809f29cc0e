"""forest.gpkg from the tiles' GeoPackages: every layer concatenated, IDs rewritten, styles carried.

:func:`merge_gpkg` merges finished parts at once; :class:`OrderedMerge` merges them while a run's
tiles are still being processed, in the run's order.  Both build on :class:`~.gpkg.GpkgMerge`.
"""
from __future__ import annotations

from pathlib import Path
from typing import Dict, Optional, Sequence

from ..atomic import atomic_path, move_into_place, temporary_beside
from .gpkg import GpkgMerge, default_styles

#: The layers of a run's forest.gpkg, in the order QGIS lists them.
LAYERS = ("trees", "tree_tops", "crowns", "crown_points", "stem_points", "skeletons", "models_3d", "crowns_3d")


def merge_gpkg(parts: Sequence[Path], path, id_maps: Optional[Sequence[dict]] = None) -> Path:
    """Concatenate the layers of per-tile GeoPackages into one at ``path`` (:class:`~.io.gpkg.GpkgMerge`).

    The result conforms to GeoPackage 1.2 (GDAL's ``validate_gpkg.py``), has an
    R-tree per geometry column and carries Sylva's QGIS styles in ``layer_styles``.

    ``id_maps`` (one {old: new} per part) rewrites ``tree_id`` values on the way.
    The 3D layers (``models_3d``, core/export/gpkg3d.py; ``crowns_3d``, core/export/crowns3d.py)
    are written per tile by the pipeline and merged here like the others.
    """
    parts = [Path(p) for p in parts]
    id_maps = list(id_maps or [{}] * len(parts))
    with atomic_path(path) as tmp:
        merge = GpkgMerge(tmp, styles=default_styles(LAYERS))
        try:
            for part, mapping in zip(parts, id_maps):
                merge.remap(merge.add(part), mapping)
        except BaseException:
            merge.abort()
            raise
        merge.close()
    return Path(path)


class OrderedMerge:
    """Merges the tiles' GeoPackages into ``forest.gpkg`` while the tiles are processed.

    Parts are appended in ``order`` (the run's deterministic processing order,
    so the merged rows do not depend on which worker finished first) as each
    becomes :meth:`ready`; :meth:`step` appends the next one when the main
    process has nothing else to do (the pool runners call it while they wait),
    so the merge of the first parts overlaps the work on the last ones.  No
    thread: the pools fork their workers from this process (Sylva, not in a
    paper).  :meth:`finish` appends the rest; :meth:`remap` rewrites IDs;
    :meth:`commit` moves the file into place; leaving the ``with`` block on an
    exception (an error or a cancel) removes it.
    """

    def __init__(self, path: Path, order: Sequence[str]):
        self.path = Path(path)
        self.tmp = temporary_beside(self.path)
        self.merge = GpkgMerge(self.tmp, styles=default_styles(LAYERS))
        self.order = list(order)
        self.next = 0
        self.parts: Dict[str, Optional[Path]] = {}
        self.ranges: Dict[str, Dict[str, tuple]] = {}

    def __enter__(self):
        return self

    def __exit__(self, kind, value, tb):
        if kind is not None:
            self.merge.abort()
            self.tmp.unlink(missing_ok=True)
        return False

    def ready(self, name: str, part: Optional[Path]) -> None:
        """Tile ``name`` is final: its GeoPackage ``part``, or None when it failed."""
        self.parts[name] = part

    def step(self) -> bool:
        """Append the next part in order if it is ready; False when there was none to append."""
        if self.next >= len(self.order) or self.order[self.next] not in self.parts:
            return False
        name = self.order[self.next]
        self.next += 1
        if self.parts[name] is not None:
            self.ranges[name] = self.merge.add(self.parts[name])
        return True

    def finish(self) -> None:
        while self.step():
            pass

    def remap(self, name: str, mapping: dict) -> None:
        self.merge.remap(self.ranges.get(name, {}), mapping)

    def commit(self) -> Optional[Path]:
        """The merged file in place (None, and nothing written, when no part was merged)."""
        self.merge.close()
        if self.merge.parts == 0:
            self.tmp.unlink()
            return None
        move_into_place(self.tmp, self.path)
        return self.path
