"""3D models of every segmented tree: sylva:reconstructtrees."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.progress import scaled
from ..core.reconstruct import GreedySkeleton, GuidedGrowth
from ..core.table import VectorTable
from .common import build_method, crs_override, input_cloud, leaves_param, lod_param, method_params
from .spec import (ENUM, FILE_OUT, FOLDER_OUT, LINE, NO_GEOMETRY, NUMBER_RESULT, VECTOR_OUT,
                   Algorithm, Feedback, Param, Result)

METHODS = ("hybrid", "greedy", "guided", "dense", "auto", "completed", "yan")

GREEDY_PARAMS = method_params(GreedySkeleton, {
    "voxel_m": ("thinning voxel (m)", "Voxel pitch of the thinning, d_l of Hu et al. 2017 (§5.1, §6.2: 0.2 m)."),
    "radius_m": ("neighbourhood radius (m)", "Fixed-radius search of the point graph, r_p of Hu et al. 2017 "
                 "(§5.2, Algorithm 1)."),
    "k": ("nearest neighbours", "kNN links (k of Hu et al. 2017 §5.2; Table 1: 10–30) added where the radius "
          "finds too few."),
    "theta_upper_deg": ("upper branch angle (°)", "Direction field: minimum angle θ_u of upper branches (Hu et "
                        "al. 2017 §5.3, Eq. 5)."),
    "theta_lower_deg": ("lower branch angle (°)", "Direction field: minimum angle θ_l of lower branches (Hu et "
                        "al. 2017 §5.3, Eq. 5)."),
    "k1": ("angle change above crown centre", "Direction field: change rate k1 above the crown centre (Hu et "
           "al. 2017, Eq. 5)."),
    "k2": ("angle change below crown centre", "Direction field: change rate k2 below the crown centre (Hu et "
           "al. 2017, Eq. 5)."),
    "alpha_max_deg": ("largest bend to a child branch (°)", "α_max: largest bend between a branch and its child "
                      "(Hu et al. 2017 §5.4)."),
    "beta_max_deg": ("largest deviation from the field (°)", "β_max: largest deviation from the direction field "
                     "(Hu et al. 2017 §5.4)."),
    "phi_max_deg": ("sibling pruning angle (°)", "φ_max: pruning angle between sibling branches (Hu et al. "
                    "2017 §5.4)."),
}, advanced=("voxel_m", "radius_m", "k", "theta_upper_deg", "theta_lower_deg", "k1", "k2", "alpha_max_deg",
             "beta_max_deg", "phi_max_deg"),
   ranges={"voxel_m": (0.01, 5.0), "radius_m": (0.05, 20.0), "k": (1, 1000), "theta_upper_deg": (-90.0, 90.0),
           "theta_lower_deg": (-90.0, 90.0), "k1": (0.01, 100.0), "k2": (0.01, 100.0),
           "alpha_max_deg": (1.0, 180.0), "beta_max_deg": (1.0, 180.0), "phi_max_deg": (1.0, 180.0)},
   prefix="Greedy skeleton: ")

GUIDED_PARAMS = method_params(GuidedGrowth, {
    "step_m": ("growth step (m)", "Internode length l of Guo et al. 2018 (§5.2)."),
    "kill_distance_m": ("kill distance (m)", "Points this close to a branch are reached: d_k of Guo et al. 2018 "
                        "(§5.2)."),
    "tropism": ("tropism weight", "Weight β of the upward tendency in the growth direction (Guo et al. 2018, "
                "Eq. 9)."),
}, advanced=("step_m", "kill_distance_m", "tropism"),
   ranges={"step_m": (0.01, 10.0), "kill_distance_m": (0.01, 20.0), "tropism": (0.0, 10.0)},
   prefix="Guided growth: ")

METHOD_LABELS = ("Hybrid: greedy skeleton, guided growth where it fails", "Greedy skeleton (airborne scans)",
                 "Guided growth through the points", "Dense scans: wood fitted to the points",
                 "Automatic: dense where the scan is dense", "Completed: hybrid plus grown small branches",
                 "Variational k-means (B-spline branches)")


def _methods(args):
    """(method, dense_method) for ModelOptions from the METHOD choice."""
    from ..core.reconstruct import Hybrid, VariationalKMeans
    from ..core.reconstruct.levelset import LevelSetQSM

    greedy = build_method(GreedySkeleton, args)
    guided = build_method(GuidedGrowth, args)
    hybrid = Hybrid(primary=greedy, fallback=guided)
    # Dense scans: geodesic level sets with circles fitted to the points and the wood swept along them
    # (benchmarks/dense.py measures the written GLB: closer to the points than AdTree's on the TLS trees).
    # "yan": Yan et al.'s variational k-means with the preset measured best on thick stems.
    dense = LevelSetQSM()
    yan = VariationalKMeans.dense_scan()
    if args["METHOD"] == "completed":
        from ..core.reconstruct.sketch import SketchCompletion

        return SketchCompletion(primary=hybrid), None
    return {"hybrid": (hybrid, None), "greedy": (greedy, None), "guided": (guided, None),
            "dense": (dense, None), "auto": (hybrid, dense), "yan": (yan, None)}[args["METHOD"]]


def run(args: dict, feedback: Feedback) -> Result:
    from ..core.export.gltf import write_glb
    from ..core.export.model import ExportFrame, TreeModel
    from ..core.forest import ModelOptions, model_trees, qsm_tables, skeleton_table
    from ..core.measure import tree_metrics

    cloud, labels = load_trees(args, feedback)
    metrics = tree_metrics(cloud, labels)
    feedback.info(f"{len(metrics)} trees to model")
    method, dense = _methods(args)
    options = ModelOptions(method=method, dense_method=dense, lod=args["LOD"], leaves=args["LEAVES"])
    trees = model_trees(cloud, labels, metrics, options, progress=scaled(feedback.progress, 0.05, 0.85),
                        cancelled=feedback.cancelled)
    columns = metrics.columns()
    for key in trees[0].record:
        if key != "tree_id":
            columns[key] = np.array([t.record[key] for t in trees])
    result = Result(values={"TREE_COUNT": len(trees)})
    if args.get("MODELS"):
        feedback.progress(0.9, "writing the 3D models")
        models = [TreeModel(t.tree_id, np.array([t.record["base_x"], t.record["base_y"], t.record["base_z"]]),
                            t.wood, t.leaves, {**{k: columns[k][i] for k in columns}})
                  for i, t in enumerate(trees)]
        write_glb(models, args["MODELS"], ExportFrame.from_cloud(cloud), cancelled=feedback.cancelled)
        result.files["MODELS"] = args["MODELS"]
        columns["model_file"] = np.array([Path(args["MODELS"]).name] * len(trees), dtype=object)
    result.vectors["TREES"] = VectorTable("trees", NO_GEOMETRY, None, columns, cloud.crs)
    result.vectors["SKELETONS"] = skeleton_table(trees, cloud, cloud.crs)
    feedback.progress(0.95, "quantitative structure models")
    cylinders, branches, qsm_trees = qsm_tables(trees, cloud, cloud.crs)
    result.vectors["CYLINDERS"] = cylinders
    result.vectors["BRANCHES"] = branches
    if args.get("QSM_FOLDER"):
        _write_qsm_folder(args["QSM_FOLDER"], cylinders, branches, qsm_trees)
        result.files["QSM_FOLDER"] = args["QSM_FOLDER"]
        feedback.info(f"QSM tables written to {args['QSM_FOLDER']}: cylinders.csv, branches.csv, trees.csv")
    counts = {m: sum(t.record["method"] == m for t in trees) for m in sorted({t.record["method"] for t in trees})}
    feedback.info("methods used: " + ", ".join(f"{m} {n}" for m, n in counts.items()))
    feedback.progress(1.0, "done")
    return result


#: A cloud without treeID that spans at most this many metres across is one tree (a single-tree scan).
SINGLE_TREE_MAX_M = 40.0


def load_trees(args: dict, feedback: Feedback):
    """(cloud without noise, with ``height`` above ground; int64 treeID labels) of INPUT.

    A segmented tile (treeID) as :func:`~.common.load_segmented` reads it; a scan without treeID that
    spans at most :data:`SINGLE_TREE_MAX_M` is one tree (label 1).  Without a CRS the coordinates are
    a local engineering frame in metres (models and tables are written in it).  Without ground points
    a single tree stands on its lowest points: height = z - the lowest z.
    """
    from ..core.errors import InputError
    from ..core.io import read_cloud
    from ..core.terrain import ground_mask, normalize
    from .common import drop_noise

    source = read_cloud(args["INPUT"], crs=args.get("CRS") or None)
    name = Path(args["INPUT"]).name
    frame = (f"CRS {source.crs.name}" if source.crs is not None else
             "no CRS: a local engineering frame, models and tables are written in the file's coordinates")
    feedback.info(f"{name}: {len(source):,} points, {frame}, units {source.units.describe()}")
    single = "treeID" not in source.attrs
    if single:
        span = np.ptp(source.local_xyz()[:, :2], axis=0) if len(source) else np.zeros(2)
        if span.max() > SINGLE_TREE_MAX_M:
            raise InputError(f"{args['INPUT']}: the point cloud has no treeID dimension and spans "
                             f"{span[0]:.0f} m x {span[1]:.0f} m, more than one tree; run 'Segment trees' "
                             "(sylva:segmenttrees; METHOD stems, or auto, for a terrestrial plot scan) on it first")
        feedback.info(f"{name}: no treeID dimension: modelled as one tree (a single-tree scan, "
                      f"{span[0]:.1f} m x {span[1]:.1f} m)")
        source = source.with_attrs(treeID=np.ones(len(source), dtype=np.int32))
    cloud, _ = drop_noise(source, feedback)
    if len(cloud) == 0:
        raise InputError(f"{args['INPUT']}: no points left once noise is removed: there is no tree to model")
    if cloud.attr("height") is None:
        feedback.progress(0.02, "height above ground")
        if single and not ground_mask(cloud).any():
            z = cloud.local_xyz()[:, 2]
            base = float(z.min())
            feedback.info(f"{name}: no ground points: the tree stands on its lowest points "
                          f"(z = {cloud.from_local(np.array([[0.0, 0.0, base]]))[0, 2]:.2f})")
            cloud = cloud.with_attrs(height=z - base)
        else:
            cloud = normalize(cloud)
    labels = np.asarray(cloud.attrs["treeID"]).astype(np.int64)
    if not (labels > 0).any():
        raise InputError(f"{args['INPUT']}: no point has a treeID above 0: there is no tree to model")
    return cloud, labels


def _write_qsm_folder(folder, cylinders, branches, trees) -> None:
    """cylinders.csv, branches.csv and trees.csv (TreeQSM-like) in ``folder`` (created), each atomically."""
    from ..core.errors import InputError
    from ..core.qsm import write_table_csv

    path = Path(folder)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{folder}: cannot create the QSM folder ({exc.strerror})") from None
    for name, table in (("cylinders", cylinders), ("branches", branches), ("trees", trees)):
        write_table_csv(path / f"{name}.csv", table)


RECONSTRUCT_TREES = Algorithm(
    id="reconstructtrees",
    name="Reconstruct trees",
    group="Individual trees",
    group_id="trees",
    summary=(
        "Builds a 3D model of every tree of a segmented tile (a treeID per point, as 'Segment trees' "
        "writes it). METHOD hybrid (default) follows Hu et al. (2017, §6.2): the greedy skeleton of "
        "§4.2–§5.4 (trunk points added, voxel thinning, neighbourhood graph, direction field, "
        "priority-queue growth), and, for trees where it reaches under 85 % of the points or its graph "
        "is broken, Guo et al. (2018)'s point-guided space colonisation with crown filling; so every "
        "tree gets a model. Branch radii follow the pipe model (Hu Eq. 6) scaled to the tree's DBH "
        "(measured by a circle fit at 1.3 m when the stem is scanned densely enough, else from height "
        "and crown diameter by Jucker et al. 2017). METHOD dense is Yan et al. (2009): variational k-means "
        "clusters with bounding cylinders, a branch graph and B-spline branches, for terrestrial or "
        "below-canopy scans; auto picks it for the trees dense enough. Outputs: one GLB with a named node "
        "per tree (bark and leaf materials, georeferenced), skeleton lines with the radius as M, the trees "
        "table with the model's measurements, and a quantitative structure model (QSM) per tree like "
        "TreeQSM's: cylinders (3D lines) and branches tables, optionally as CSV files too. Dense trees get "
        "the cylinders of their B-spline branches and a DBH measured at 1.3 m; other trees one cylinder per "
        "skeleton segment with the model's radii (column qsm_method says which)."
    ),
    params=(
        input_cloud(" A segmented tile carries a treeID dimension (0 = no tree); a scan of one tree "
                    "(LAS/LAZ, text or PLY, with or without ground points or CRS) is modelled as one tree "
                    "standing on its lowest stem points."),
        Param("METHOD", ENUM, "Reconstruction method", options=METHODS, default="auto", labels=METHOD_LABELS,
              help="auto (default): dense for trees scanned densely enough (8th neighbour within 0.25 m, "
                   "lower stem scanned: terrestrial, mobile or drone scans), hybrid for the others; "
                   "hybrid: greedy skeleton, guided growth where it fails (Hu §6.2); greedy: Hu et al. "
                   "only; guided: Guo et al. only; dense: wood fitted to the points (geodesic level sets "
                   "of the scan, a circle fitted to every cross-section, tubes swept along them; no leaf "
                   "cards unless LEAVES asks for them); completed: hybrid, then small branches grown by "
                   "self-similarity (the sketch paper §6, Table 1 angles) inside the crown's silhouettes "
                   "seen from the south and from the east, for fuller crowns where the scan saw only the "
                   "main branches; yan: Yan et al. (2009) variational k-means with B-spline branches. Each method's own settings are under Advanced parameters, named after it."),
        *GREEDY_PARAMS,
        *GUIDED_PARAMS,
        lod_param(),
        leaves_param(help="auto: needle clusters on conical crowns, leaf cards (phyllotaxis, Hu §5.6) otherwise; "
                          "none on wood fitted to a dense scan."),
        crs_override(),
        Param("MODELS", FILE_OUT, "3D models (GLB)", file_filter="glTF binary (*.glb)", optional=True,
              help="One GLB for the tile, a node per tree named tree_<id>, with a .prj and an origin sidecar."),
        Param("SKELETONS", VECTOR_OUT, "Skeletons", geometry=LINE,
              help="MultiLineStringZM per tree: one part per branch chain, M = branch radius (m)."),
        Param("TREES", VECTOR_OUT, "Trees table", geometry=NO_GEOMETRY,
              help="The segmentation's fields plus base_x/y/z, dbh, dbh_source, n_branches, "
                   "total_branch_length, wood_volume, method, visited_fraction, quality, leaves, flags, "
                   "qsm_method (fitted_cylinders: the dense method's cylinders fitted to the points; bspline_cylinders: Yan et al. cylinders; skeleton_edges: a cylinder per "
                   "skeleton segment), n_cylinders, trunk_volume and total_volume (m³, sums of the QSM's "
                   "cylinders), n_branches_order_1..3 and branch_counts (order:count for every order), "
                   "model_file."),
        Param("CYLINDERS", VECTOR_OUT, "QSM cylinders", geometry=LINE, optional=True,
              help="One 3D line per cylinder from its start to its end (TreeQSM-like): tree_id, id, parent "
                   "(cylinder id, -1 at the stem base), branch, order (0 stem), start_x/y/z (CRS units), "
                   "axis_x/y/z (unit vector), length and radius (m)."),
        Param("BRANCHES", VECTOR_OUT, "QSM branches", geometry=NO_GEOMETRY, optional=True,
              help="One row per branch: tree_id, id, parent (branch id, -1 for the stem), order, "
                   "n_cylinders, length (m), base_diameter (m), volume (m³), angle_deg to the parent "
                   "cylinder, base_height (z of its start, CRS units)."),
        Param("QSM_FOLDER", FOLDER_OUT, "QSM tables (CSV folder)", optional=True,
              help="A folder with cylinders.csv, branches.csv (as the two layers) and trees.csv (tree_id, "
                   "dbh_m, dbh_source, height_m, trunk_volume_m3, total_volume_m3, n_cylinders, "
                   "branches_order<o> per order, qsm_method)."),
    ),
    run=run,
    results=(Param("TREE_COUNT", NUMBER_RESULT, "Number of trees", help="Trees modelled."),),
)

ALGORITHMS = (RECONSTRUCT_TREES,)
