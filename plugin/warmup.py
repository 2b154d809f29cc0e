"""Compile every numba kernel once, so that a user's first run is not a minute of silence.

The kernels (:mod:`sylva.core.jit`) are compiled on first call for the argument types of that call and the
machine code is cached on disk; a run of every algorithm on a small corner of the bundled sample therefore
compiles (and caches) each kernel with the types the real runs use. ``scripts/setup.sh`` runs it
(``python -m sylva.plugin.warmup``), and the plugin runs it in a background task on its first load in the
QGIS desktop. A stamp beside the cache records that it was done for this Sylva, numba and Python, so later
loads skip it. No QGIS import here: it runs in any Python with Sylva's dependencies.
"""
from __future__ import annotations

import hashlib
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable, Optional

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "resources" / "sample" / "sample.laz"
CORNER_M = 40.0
#: (algorithm id, extra parameters): every algorithm, and the methods whose kernels differ.
RUNS = (
    ("canopyheightmodel", {}), ("treetops", {}), ("treetops", {"INPUT": "{chm}"}),
    ("normalizeheight", {"CLASSIFY_GROUND": "always"}),
    ("normalizeheight", {"CLASSIFY_GROUND": "always", "GROUND_METHOD": "csf", "INTERPOLATION": "knnidw"}),
    ("segmenttrees", {"CONCAVITY": "0.3", "HULL": "concave", "GROWTH": "open-grown"}),
    ("segmenttrees", {"METHOD": "chm"}),
    ("reconstructtrees", {"INPUT": "{segmented}", "METHOD": "auto"}),
    ("reconstructtrees", {"INPUT": "{segmented}", "METHOD": "completed", "LOD": "1"}),
    ("reconstructtrees", {"INPUT": "{segmented}", "METHOD": "dense", "LOD": "2"}),
    ("exportmodels", {"INPUT": "{models}"}), ("billboards", {"INPUT": "{segmented}"}),
    ("treefromsketch", {}), ("pipeline", {"BILLBOARDS": "true"}),
)


def stamp_path() -> Path:
    """Where the 'kernels compiled' stamp lives: beside numba's cache when NUMBA_CACHE_DIR is set, else in
    the kernels' own __pycache__ when writable, else in the user's cache folder.

    A NUMBA_CACHE_DIR cache is keyed by the path the sources were imported from (QGIS loads the plugin
    through its plugin folder, the ``sylva`` command from the checkout): the stamp there names that path
    too, so a warm-up through one path does not vouch for the other."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        imported_from = str(Path(os.path.abspath(__file__)).parents[1])
        return Path(os.environ["NUMBA_CACHE_DIR"]) / f"sylva-warm-{hashlib.sha256(imported_from.encode()).hexdigest()[:12]}.json"
    own = ROOT / "core" / "__pycache__"
    try:
        own.mkdir(exist_ok=True)
        if os.access(own, os.W_OK):
            return own / "sylva-warm.json"
    except OSError:
        pass
    return Path(os.path.expanduser("~/.cache")) / "sylva" / "sylva-warm.json"


def fingerprint() -> str:
    """Changes when a kernel's source, numba or Python changes (then numba recompiles anyway)."""
    try:
        import numba
        version = numba.__version__
    except ImportError:
        version = "none"
    h = hashlib.sha256(f"{sys.version_info[:3]} {version} {sys.platform}".encode())
    for path in sorted((ROOT / "core").rglob("*.py")):
        h.update(f"{path.relative_to(ROOT)} {path.stat().st_mtime_ns} {path.stat().st_size}".encode())
    return h.hexdigest()[:16]


def is_warm() -> bool:
    try:
        return json.loads(stamp_path().read_text()).get("fingerprint") == fingerprint()
    except (OSError, ValueError):
        return False


def _sketch_layers(folder: Path) -> dict:
    import numpy as np
    import pyproj
    import shapely

    from ..core.io.gpkg import write_gpkg
    from ..core.table import VectorTable

    front = [shapely.LineString([(100, 0), (100, 300), (102, 500)]), shapely.LineString([(101, 250), (60, 330)]),
             shapely.LineString([(90, 380), (160, 460)])]
    side = [shapely.LineString([(0, 0), (5, 250), (10, 520)]), shapely.LineString([(4, 200), (60, 300)])]
    crown = shapely.Polygon([(0, 80), (200, 80), (200, 560), (0, 560)])
    out = {}
    for name, geoms, kind, crs in (("front", front, "line", None), ("side", side, "line", None),
                                   ("front_silhouette", [crown], "polygon", None),
                                   ("location", [shapely.Point(500123.0, 5700456.0, 80.0)], "point",
                                    pyproj.CRS.from_epsg(25832))):
        path = folder / f"{name}.gpkg"
        write_gpkg(path, [VectorTable(name, kind, np.array(geoms, dtype=object), {"id": np.arange(len(geoms))},
                                      crs, has_z=kind == "point")])
        out[name.upper()] = str(path)
    return out


def _apex_edge() -> None:
    """The clean-up step the sample's corner does not reach (a point of a crown's edge above its
    tree's apex, beside a taller neighbour: :func:`~sylva.core.segment.ncut.cleanup.apex_near_top`),
    on arrays of the types a segmentation gives it."""
    import numpy as np

    from ..core.segment.ncut.cleanup import apex_near_top

    local = np.array([[0.0, 0.0, 10.0], [3.0, 0.0, 12.0], [3.5, 0.0, 11.9], [5.0, 0.0, 14.0]])
    labels = np.array([1, 1, 2, 2], dtype=np.int32)
    apex_near_top(local[:, :2], local[:, 2], labels, np.array([[0.0, 0.0], [5.0, 0.0]]), np.array([1, 2]),
                  np.array([1.0, 1.0]))


def warm_up(progress: Optional[Callable[[float, str], None]] = None,
            cancelled: Optional[Callable[[], bool]] = None) -> dict:
    """Run every algorithm on a corner of the sample (compiling and caching the kernels); write the stamp.

    Returns {"seconds", "compile_seconds", "kernels", "compiled", "unused": [names]}."""
    import importlib
    import pkgutil

    from .. import cli
    from ..algorithms import get
    from ..algorithms.spec import Feedback
    from ..core import jit
    from ..core.io import read_cloud
    from ..core.io.las import write_las
    from ..core.segment import segment_trees
    from ..core.terrain import normalize

    t0 = time.perf_counter()
    c0 = jit.compile_seconds()
    from .. import core

    for info in pkgutil.walk_packages(core.__path__, core.__name__ + "."):   # register every kernel
        try:
            importlib.import_module(info.name)
        except ImportError:   # an optional dependency (dask) that this Python lacks
            pass
    report = progress or (lambda f, m="": None)
    with tempfile.TemporaryDirectory(prefix="sylva-warmup-") as tmp:
        work = Path(tmp)
        cloud = read_cloud(SAMPLE)
        x0, y0 = cloud.xyz[:, 0].min(), cloud.xyz[:, 1].min()
        corner = cloud.subset((cloud.xyz[:, 0] < x0 + CORNER_M) & (cloud.xyz[:, 1] < y0 + CORNER_M))
        write_las(work / "corner.laz", corner)
        report(0.02, "segmenting a corner of the sample")
        write_las(work / "segmented.laz", corner, extra={"treeID": segment_trees(normalize(corner))})
        names = {"chm": str(work / "chm.tif"), "segmented": str(work / "segmented.laz"),
                 "models": str(work / "models.glb")}
        for k, (alg_id, extra) in enumerate(RUNS):
            if cancelled is not None and cancelled():
                break
            report(0.05 + 0.9 * k / len(RUNS), f"compiling the kernels of {alg_id} ({k + 1} of {len(RUNS)})")
            alg = get(alg_id)
            raw = {"INPUT": str(work / "corner.laz")} if any(p.name == "INPUT" for p in alg.params) else {}
            if alg_id == "treefromsketch":
                raw.update(_sketch_layers(work))
            raw.update({key: value.format(**names) for key, value in extra.items()})
            for p in alg.outputs:
                target = work / f"{alg_id}-{k}-{p.name.lower()}{p.default_extension()}"
                raw[p.name] = str(target)
            if alg_id == "canopyheightmodel":
                raw["OUTPUT"] = names["chm"]
            if alg_id == "reconstructtrees" and extra.get("METHOD") == "auto":
                raw["MODELS"] = names["models"]
            args = cli.convert(alg, raw)
            result = alg.run(args, Feedback())
            cli.write_outputs(alg, args, result)
        _apex_edge()
    kernels = jit.kernels()
    used = [k for k in kernels if k.compiled is not None and getattr(k.compiled, "signatures", [True])]
    summary = {"seconds": round(time.perf_counter() - t0, 1), "compile_seconds": round(jit.compile_seconds() - c0, 1),
               "kernels": len(kernels), "compiled": len(used),
               "unused": sorted(f"{k.__module__}.{k.__name__}" for k in kernels if k not in used)}
    if cancelled is None or not cancelled():
        path = stamp_path()
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"fingerprint": fingerprint(), **summary}, indent=1))
    report(1.0, "kernels ready")
    return summary


def main(argv=None) -> int:
    import argparse

    parser = argparse.ArgumentParser(prog="python -m sylva.plugin.warmup", description=__doc__.split("\n\n")[0])
    parser.add_argument("--if-needed", action="store_true", help="do nothing when the stamp says it was done")
    parser.add_argument("--progress", action="store_true",
                        help="also print 'progress FRACTION MESSAGE' lines (the QGIS plugin reads them)")
    ns = parser.parse_args(argv)
    if ns.if_needed and is_warm():
        print("sylva warm-up: kernels already compiled and cached")
        return 0
    print("sylva warm-up: compiling Sylva's kernels once (about a minute on 2 cores; later runs load the cache)...",
          flush=True)
    s = warm_up(progress=(lambda f, m="": print(f"progress {f:.3f} {m}", flush=True)) if ns.progress else None)
    print(f"sylva warm-up: {s['compiled']} of {s['kernels']} kernels compiled or loaded in {s['seconds']} s "
          f"({s['compile_seconds']} s compiling)" + (f"; not reached by the warm-up: {', '.join(s['unused'])}"
                                                     if s["unused"] else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
