"""A tree from two sketched profiles (the sketch paper, §4–§7): sylva:treefromsketch."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.geometry import DEFAULT_LOD
from ..core.reconstruct.sketch import SketchTree
from .common import build_method, leaves_param, lod_param, method_params
from .spec import (FILE_OUT, LINE, NUMBER, NUMBER_RESULT, POINT, POLYGON, VECTOR,
                   VECTOR_OUT, Algorithm, Feedback, Param, Result)

SKETCH_PARAMS = method_params(SketchTree, {
    "sigma": ("Copied share of the parent branch (0–1)", "Small branches copy the first σ of their parent "
              "branch's nodes (the sketch paper §6, Eq. 8; Table 1: 0.3)."),
    "cos_theta1": ("Branch angle: smallest cosine", "Smallest cosine of the angle θ between a small branch and "
                   "its parent (θ1 of Table 1: 0.5, i.e. at most 60°)."),
    "cos_theta2": ("Branch angle: largest cosine", "Largest cosine of that angle (θ2 of Table 1: 0.9, i.e. at "
                   "least 26°)."),
    "cos_phi1": ("Angle between successive branches: smallest cosine", "Smallest cosine of the angle φ between "
                 "two successive small branches of one branch (φ1 of Table 1: −0.5, i.e. at most 120°)."),
    "cos_phi2": ("Angle between successive branches: largest cosine", "Largest cosine of that angle (φ2 of "
                 "Table 1: 0.5, i.e. at least 60°)."),
    "levels": ("Small branch generations", "Generations l of small branches grown from the drawn ones "
               "(Table 1: 2; 0 keeps the drawn branches only)."),
    "buds_per_branch": ("Buds per branch", "Candidate small branches per branch before crowded buds "
                        "are removed (Sylva, not in the paper: 8)."),
    "crowd_radius_fraction": ("Crowding radius (share of height)", "A bud is dropped when more than "
                              "CROWD_MAX small-branch nodes lie within this share of the tree height."),
    "crowd_max": ("Crowding limit (nodes)", "See CROWD_RADIUS_FRACTION."),
    "step_fraction": ("Resampling step (share of height)", "Strokes are resampled at this share of the "
                      "tree height before depth retrieval (0.01: a node every 1 %)."),
    "snap_fraction": ("Snapping tolerance (share of height)", "A stroke end this close to another stroke "
                      "(share of the drawing's height) is joined to it."),
    "seed": ("Random seed", "Seed of the small-branch angles: the same inputs and seed give the same tree."),
}, advanced=("sigma", "cos_theta1", "cos_theta2", "cos_phi1", "cos_phi2", "buds_per_branch",
             "crowd_radius_fraction", "crowd_max", "step_fraction", "snap_fraction"),
   ranges={"sigma": (0.01, 1.0), "cos_theta1": (-1.0, 1.0), "cos_theta2": (-1.0, 1.0), "cos_phi1": (-1.0, 1.0),
           "cos_phi2": (-1.0, 1.0), "levels": (0, 6), "buds_per_branch": (0, 100),
           "crowd_radius_fraction": (0.001, 0.999), "crowd_max": (0, 10000), "step_fraction": (0.001, 0.5),
           "snap_fraction": (0.001, 0.5), "seed": (0, 2 ** 31 - 1)})


def _geometries(table, what: str):
    from ..core.errors import EmptyInputError

    if table is None:
        return None
    geoms = [g for g in (table.geometries if table.geometries is not None else []) if g is not None and not g.is_empty]
    if not geoms:
        raise EmptyInputError(f"{what}: the layer is empty (no feature with a geometry)")
    return geoms


def _location(table, feedback: Feedback):
    """(x, y, z) of the first point of LOCATION and its CRS."""
    import shapely

    from ..core.errors import CRSError, InputError

    geoms = _geometries(table, f"LOCATION ({table.name})")
    pts = [p for g in geoms for p in shapely.get_parts(g) if p.geom_type == "Point" and not p.is_empty]
    if not pts:
        raise InputError(f"LOCATION ({table.name}): the layer holds no point")
    if len(pts) > 1:
        feedback.warn(f"LOCATION ({table.name}) holds {len(pts)} points; the tree stands at the first one")
    x, y, z = shapely.get_coordinates(pts[0], include_z=True)[0]   # not .z / .has_z: see core.reconstruct.sketch.strokes.vertices_xy
    z = z if np.isfinite(z) else 0.0
    crs = table.crs
    if crs is not None and crs.is_geographic:
        raise CRSError(f"LOCATION ({table.name}): its CRS {crs.name} is geographic (degrees); "
                       "save the location in a projected CRS (metres or feet), e.g. the local UTM zone")
    if crs is None:
        feedback.warn(f"LOCATION ({table.name}) has no CRS: the outputs are in a local frame")
    return np.array([x, y, z], dtype=np.float64), crs


def build_geometry(skeleton, height_m: float, leaves: str = "auto", lod: int = DEFAULT_LOD, seed: int = 0):
    """Radii (pipe model scaled to an allometric DBH), wood mesh and leaves of a sketched tree.

    Returns (skeleton with radii, wood mesh, leaf mesh or None, record dict).
    """
    from ..core.forest import ModelOptions, dbh_radii, is_conical, leaf_mesh
    from ..core.geometry import branch_count, simplify_skeleton, total_branch_length, tree_mesh, with_radii, wood_volume
    from ..core.measure import allometric_dbh_m

    options = ModelOptions(lod=lod, leaves=leaves)
    sk = simplify_skeleton(skeleton, options.simplify_m) if options.simplify_m > 0 else skeleton
    xy = sk.nodes[:, :2]
    crown_d = float(np.mean(np.ptp(xy, axis=0))) if len(sk) > 1 else 0.0
    dbh = float(allometric_dbh_m(height_m, crown_d))
    sk = with_radii(sk, dbh_radii(sk, dbh, options))
    wood = tree_mesh(sk, lod=options.lod)
    forks = sk.nodes[sk.n_children() >= 2, 2]
    crown_base = float(forks.min()) if len(forks) else 0.0
    kind = options.leaves
    if kind == "auto":
        kind = "needles" if is_conical(sk.nodes, crown_base) else "broadleaf"
    leaves_mesh = leaf_mesh(sk, kind, options, seed=seed)
    record = {
        "height": float(sk.nodes[:, 2].max()) if len(sk) else 0.0,
        "crown_diameter": crown_d,
        "crown_base_height": crown_base,
        "dbh": dbh,
        "dbh_source": "allometric",
        "n_branches": int(branch_count(sk)),
        "total_branch_length": float(total_branch_length(sk)),
        "wood_volume": float(wood_volume(sk)),
        "leaves": kind,
    }
    return sk, wood, leaves_mesh, record


def run(args: dict, feedback: Feedback) -> Result:
    import shapely

    from ..core.errors import InputError
    from ..core.export.gltf import write_glb
    from ..core.export.model import ExportFrame, TreeModel
    from ..core.geometry import branches
    from ..core.progress import scaled
    from ..core.reconstruct.sketch import tree_from_sketch
    from ..core.table import VectorTable, multilinestring_zm_wkb

    height = args.get("HEIGHT_M")
    if height is None or not np.isfinite(height) or height <= 0:
        raise InputError(f"HEIGHT_M: the tree height must be a positive number of metres, got {height!r}")
    tables = {k: args.get(k) for k in ("FRONT", "SIDE", "FRONT_SILHOUETTE", "SIDE_SILHOUETTE", "LOCATION")}
    for k in ("FRONT", "SIDE", "LOCATION"):
        if tables[k] is None:
            raise InputError(f"{k}: the layer is missing: a front view, a side view and a location are needed")
    names = {k: f"{k} ({t.name})" for k, t in tables.items() if t is not None}
    geoms = {k: _geometries(t, names[k]) for k, t in tables.items() if t is not None and k != "LOCATION"}
    base, crs = _location(tables["LOCATION"], feedback)
    method = build_method(SketchTree, args)
    feedback.progress(0.02, "2D skeletons and depth retrieval")
    res = tree_from_sketch(geoms["FRONT"], geoms["SIDE"], float(height), method,
                           geoms.get("FRONT_SILHOUETTE"), geoms.get("SIDE_SILHOUETTE"),
                           float(args.get("FRONT_AZIMUTH_DEG") or 0.0), names=(names["FRONT"], names["SIDE"]),
                           progress=scaled(feedback.progress, 0.02, 0.5), cancelled=feedback.cancelled)
    for w in res.warnings:
        feedback.warn(w)
    feedback.info(f"{res.stats['n_main_nodes']} nodes of drawn branches ({res.stats['n_complementary_nodes']} from "
                  f"side-view strokes left unmatched), {res.stats['n_nodes'] - res.stats['n_main_nodes']} of small "
                  f"branches")
    feedback.progress(0.55, "wood and leaves")
    lod = int(args.get("LOD") if args.get("LOD") is not None else 1)
    sk, wood, leaves, record = build_geometry(res.skeleton, float(height), args.get("LEAVES") or "auto", lod,
                                              int(args.get("SEED") or 0))
    frame = ExportFrame(crs=crs)
    units = frame.resolved_units()
    scale = np.array([units.horizontal_m, units.horizontal_m, units.vertical_m])
    record.update(tree_id=1, method="sketch", n_main_nodes=int(res.stats["n_main_nodes"]),
                  front_azimuth_deg=float(res.azimuth_deg), base_x=float(base[0]), base_y=float(base[1]),
                  base_z=float(base[2]))
    result = Result(values={"TREE_COUNT": 1})
    if args.get("MODEL"):
        feedback.progress(0.8, "writing the 3D model")
        model = TreeModel(1, base, wood, leaves, dict(record))
        write_glb([model], args["MODEL"], frame, origin=base, cancelled=feedback.cancelled)
        result.files["MODEL"] = args["MODEL"]
        record["model_file"] = Path(args["MODEL"]).name
    chains = [c for c in branches(sk, sk.radius) if len(c) >= 2]
    parts = [np.column_stack([base + sk.nodes[c] / scale, sk.radius[c]]) for c in chains]
    result.vectors["SKELETON"] = VectorTable(
        "skeleton", LINE, np.array([multilinestring_zm_wkb(parts)], dtype=object),
        {"tree_id": np.array([1], dtype=np.int64), "n_chains": np.array([len(parts)], dtype=np.int64)},
        crs, has_m=True)
    columns = {k: np.array([v], dtype=object if isinstance(v, str) else None) for k, v in record.items()}
    columns = {"tree_id": columns.pop("tree_id"), **columns}
    result.vectors["TREES"] = VectorTable("trees", POINT, np.array([shapely.Point(*base)], dtype=object),
                                          columns, crs)
    feedback.progress(1.0, "done")
    return result


TREE_FROM_SKETCH = Algorithm(
    id="treefromsketch",
    name="Tree from two sketches",
    group="Individual trees",
    group_id="trees",
    summary=(
        "Builds a 3D tree from the main branches you digitise over two photos of it, taken from two "
        "roughly orthogonal sides (the sketch paper: Sketch-based tree modeling from two views, §4–§7). "
        "Draw the strokes in any local coordinate system, y up (e.g. over a photo loaded without CRS); "
        "strokes that cross or end on another stroke are joined. The lowest point of the trunk is the "
        "base, and each drawing is scaled so its height equals HEIGHT_M. The front drawing's horizontal "
        "axis becomes east and the side drawing's north (turned by FRONT_AZIMUTH_DEG). The 3D main "
        "branches come from depth retrieval (§5, Eq. 1–7: each front branch takes its depth from the "
        "side branch at the same heights with the closest maximum height, with branch extension and "
        "complementarity), small branches from self-similarity within the crown silhouettes (§6, "
        "Table 1), radii from the pipe model scaled to an allometric DBH, and leaves as in "
        "'Reconstruct trees'. The model is georeferenced at LOCATION and exports like any other tree."
    ),
    params=(
        Param("FRONT", VECTOR, "Front view strokes", geometry=LINE,
              help="Lines along the trunk and main branches as seen on the front photo (any units, y up)."),
        Param("SIDE", VECTOR, "Side view strokes", geometry=LINE,
              help="The same tree's trunk and main branches on a photo taken about 90° to the left or right "
                   "of the front one; its horizontal axis becomes north when FRONT_AZIMUTH_DEG is 0."),
        Param("FRONT_SILHOUETTE", VECTOR, "Front crown silhouette", geometry=POLYGON, optional=True,
              help="Polygon(s) around the crown on the front drawing (same units as FRONT); small branches "
                   "stay inside. Default: the strokes' convex hull widened by 10 % of their height, cut at the base "
                   "and the top."),
        Param("SIDE_SILHOUETTE", VECTOR, "Side crown silhouette", geometry=POLYGON, optional=True,
              help="The same for the side drawing."),
        Param("LOCATION", VECTOR, "Tree location", geometry=POINT,
              help="A point layer in a projected CRS giving the tree's base; the outputs use its CRS. When it "
                   "holds several points the first one is used (with a warning). Its z, if any, is the ground."),
        Param("HEIGHT_M", NUMBER, "Tree height (m)", default=15.0, minimum=0.5, maximum=150.0,
              help="Scales both drawings: base to top equals this height."),
        Param("FRONT_AZIMUTH_DEG", NUMBER, "Front view azimuth (°)", default=0.0, optional=True,
              minimum=-360.0, maximum=360.0,
              help="Compass bearing the front photo was taken looking along (0: looking north, so the "
                   "drawing's right is east and the side photo looks west)."),
        *SKETCH_PARAMS,
        lod_param(advanced=True),
        leaves_param(help="auto: needle clusters on a conical crown, leaf cards otherwise; none: bare wood."),
        Param("MODEL", FILE_OUT, "3D model (GLB)", file_filter="glTF binary (*.glb)", optional=True,
              help="One GLB with a node tree_1, georeferenced at LOCATION (.prj and origin sidecars)."),
        Param("SKELETON", VECTOR_OUT, "Skeleton", geometry=LINE,
              help="MultiLineStringZM: one part per branch chain, M = branch radius (m), in LOCATION's CRS."),
        Param("TREES", VECTOR_OUT, "Tree", geometry=POINT,
              help="The tree as a point at LOCATION: tree_id, height, crown_diameter, crown_base_height, dbh "
                   "(allometric), n_branches, total_branch_length, wood_volume, leaves, n_main_nodes, "
                   "model_file."),
    ),
    run=run,
    results=(Param("TREE_COUNT", NUMBER_RESULT, "Number of trees", help="Always 1."),),
)

ALGORITHMS = (TREE_FROM_SKETCH,)
