"""Dense wood models fitted to terrestrial scans: geodesic level sets, circle fits, tubes (Sylva's default).

    model = LevelSetQSM().model(TreePoints(tree_id, xyz, ground_z))

The skeleton follows the level-set idea that Yan et al. (2009) compare their
clustering with (§1.3 and §5, [XGC07]: Xu, Gossett & Chen 2007, points
binned by their shortest-path distance to the root), which is also how
TreeQSM covers a tree (Raumonen et al. 2013) and how 3DFin/dendromatics
follow stems (Cabo et al. 2018): a kNN graph of the points (k neighbours, as
Yan §2.1), shortest-path (geodesic) distances from the lowest points, the
points binned by that distance, and the connected pieces of every bin
become the skeleton's nodes; each node's parent is the node of the
predecessor of its nearest point on the shortest-path tree, so the skeleton
is a tree by construction.  Geometry is then fitted to the points, as
TreeQSM's cylinders are (Sylva, not in Yan et al.: their radii come from
bounding cylinders, §2.3):

* pieces of the same bin with the same parent whose centres are closer than
  their spreads are one cross-section seen in parts (a stem seen from a few
  scanner positions) and are merged;
* each node's axis runs from its parent's centre to its children's; its
  points, projected on the plane normal to the axis, get a least-squares
  circle (Kasa's algebraic fit refined by Gauss-Newton steps, all nodes at
  once) when they cover at least ``min_arc_deg`` of the circumference; the
  others, thin branches whose points scatter about a centre line, get the
  median distance of their points to the axis through their centroid;
* radii are smoothed along each branch (running median of three) and a
  branch starts no thicker than its parent;
* the branches (a node continues into the child carrying the most points)
  become tubes swept along their centre lines with rotation-minimising
  frames (:func:`sylva.core.geometry.sweep_tube`, Yan et al. §4.2), from
  the parent's centre to the farthest point of the tip, and the TreeQSM-like
  cylinder table of those centre lines (:mod:`sylva.core.qsm`).

Two scales (Sylva): a first pass with bins of ``bin_spacing`` point spacings gives every point the
radius of its piece; the structure (skeleton, branches, QSM) is then binned in widths of ``adaptive``
times that radius (wide bins keep a thick stem's cross-section whole, narrow ones follow twigs), and its
stubs (leaf branches that stay within three parent radii + three bins of the parent, :func:`prune_stubs`)
are dropped; the wood mesh (:mod:`.wood_mesh`, :func:`~.wood_mesh.fitted_mesh_lines`) is one tube per
run of the structure's circle-fitted cross-sections at least ``thick_m`` thick, plus the branches of a
third pass with narrow bins everywhere (``fine_spacing`` point spacings, at least ``min_bin_m``; along a
twig, nodes of fewer than ``fine_min_points`` points joined to their parent) whose points those tubes do
not cover; tubes no point is nearest to are left out (:func:`~.wood_mesh.prune_redundant`), and every tube
gets the fewest polygon sides whose chord error is within a tolerance, its polygon as far from the axis on
average as the fitted circle (:func:`~.wood_mesh.tube_mesh`).

Everything is vectorised (scipy's kd-tree, Dijkstra and connected
components; bincount sums): ~0.1–0.3 s for 10,000–20,000 points.
``benchmarks/dense.py`` measures the written GLB against the scans.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from ..circles import arc_sectors, fit_circles
from ..errors import InputError
from ..jit import njit
from ..progress import CancelCheck, Progress, check, report
from ..qsm import cylinders_from_curves, group_median
from .model import Reconstruction, Skeleton, TreePoints, screen
from .wood_mesh import fitted_mesh_lines, simplify_lines

__all__ = ["LevelSetQSM", "level_set_nodes"]


@dataclass(frozen=True)
class LevelSetQSM:
    """Geodesic level-set skeleton with radii fitted to the points (see the module docstring).

    ``k`` neighbours of the graph; ``bin_m`` width of the geodesic bins (0: ``bin_spacing`` times the
    median distance to the 8th neighbour, between ``min_bin_m`` and ``max_bin_m``; narrow bins follow
    the points closely, measured on the TLS trees by ``benchmarks/dense.py``); ``root_m`` points
    this close above the lowest point are the sources; ``merge_spacing`` (0: off) points of one bin
    closer than this many point spacings (or a bin) belong to one piece (fewer, rounder sections on thick
    stems, but farther from the points on the TLS trees); ``min_arc_deg`` smallest arc of a
    cross-section that gets a circle fit; ``min_component`` pieces of the graph with fewer
    points are left out (isolated noise); ``sides`` of the tubes (thick ones: ``sides``, twigs
    under 3 cm radius: ``twig_sides``); ``max_points`` larger trees are thinned to a voxel grid
    first; ``thick_m``, ``cover_m``, ``cover_share``: the wood mesh's fitted stem tubes and the fine
    branches kept beside them (:func:`~.wood_mesh.fitted_mesh_lines`); ``fine_min_points`` a node of the
    fine level with one child and fewer points joins its parent (:func:`level_set_nodes` ``min_points``);
    ``chord_spacing`` the LOD 0 wood mesh's polygons may lie off the fitted circle by this many point
    spacings (the median distance to the 8th neighbour) when that exceeds the LOD's own tolerance
    (:attr:`DenseModel.mesh_chord_m`; Sylva, not in the papers: a polygon finer than the scan's spacing
    shows no more of what was scanned; TLS trees 1 / 7 / 13: 2.5 / 1.5 / 8.5 cm instead of 8 mm; this
    step alone: 19,122 / 14,511 / 18,824 -> 15,525 / 12,747 / 12,952 vertices, points -> surface
    0.83 / 0.63 / 2.38 -> 0.80 / 0.61 / 2.32 cm; the synthetic trees, 2.4 cm spacing, get 1.1 cm).
    """

    k: int = 10
    bin_m: float = 0.0
    bin_spacing: float = 2.0
    min_bin_m: float = 0.02
    adaptive: float = 0.6
    fine_spacing: float = 0.25
    fine_min_points: int = 3
    thick_m: float = 0.03
    cover_m: float = 0.01
    cover_share: float = 0.2
    max_bin_m: float = 0.5
    root_m: float = 0.1
    merge_spacing: float = 0.0
    min_arc_deg: float = 150.0
    min_component: int = 5
    sides: int = 10
    twig_sides: int = 6
    max_points: int = 400_000
    min_points: int = 50
    chord_spacing: float = 0.45

    name = "level_set_qsm"
    #: model_trees takes this method's own tubes as the wood mesh
    fitted_wood = True

    def __post_init__(self):
        if self.k < 2 or self.sides < 3 or self.twig_sides < 3 or self.bin_m < 0 or not self.min_bin_m > 0:
            raise InputError("LevelSetQSM: k >= 2, sides >= 3, twig_sides >= 3, bin_m >= 0, min_bin_m > 0")

    def model(self, tree: TreePoints, progress: Progress = None, cancelled: CancelCheck = None):
        from .kmeans import DenseModel

        t0 = time.perf_counter()
        ground_z, flags, rec = screen(tree, self.min_points, self.name, progress)
        if rec is not None:
            skel = rec.skeleton
            curves = [skel.nodes] if len(skel) > 1 else []
            radii = [np.full(len(skel), 0.01)] if len(skel) > 1 else []
            bp = np.array([-1][:len(curves)])
            return DenseModel(rec, None, None, curves, radii, bp, np.zeros(len(curves), np.int64),
                              cylinders_from_curves(curves, radii, bp))
        xyz = np.asarray(tree.xyz, dtype=np.float64)
        if len(xyz) > self.max_points:
            xyz = _voxel_thin(xyz, self.max_points)
            flags.append("thinned")
        check(cancelled)
        nodes = level_set_nodes(xyz, self)
        mesh_curves = mesh_radii = None
        if self.adaptive > 0 and self.bin_m <= 0:
            # two scales: the coarse level's radii set the bin width of every point (the structure and
            # the QSM: wide bins on thick stems keep each cross-section whole), and a fine level with
            # narrow bins everywhere follows the twigs (the mesh, where the structure's stems are thin)
            coarse = nodes
            r = coarse["radius"][np.maximum(coarse["label"], 0)]
            r = np.where(coarse["label"] >= 0, r, np.median(coarse["radius"]))
            fine = float(np.clip(self.fine_spacing * coarse["spacing"], self.min_bin_m, self.max_bin_m))
            width = np.clip(self.adaptive * r, fine, max(coarse["bin_m"], fine))
            nodes = level_set_nodes(xyz, self, width=width, prep=coarse["prep"])
            nodes["bin_m"] = fine
            fn = level_set_nodes(xyz, replace(self, bin_m=fine), prep=coarse["prep"],
                                 min_points=self.fine_min_points)
        report(progress, 0.6, "level sets")
        check(cancelled)
        structure = _branches(nodes, ground_z)
        curves, radii, bparent, border, skel, _ = structure
        if self.adaptive > 0 and self.bin_m <= 0:
            mesh_curves, mesh_radii = fitted_mesh_lines(structure, nodes, _branches(fn, ground_z), fn, xyz,
                                                        self.thick_m, self.cover_m, self.cover_share)
        curves, radii, bparent, border = prune_stubs(curves, radii, bparent, border, 3 * nodes["bin_m"])
        curves, radii = simplify_lines(curves, radii)
        cyl = cylinders_from_curves(curves, radii, bparent, border)
        stats = {"n_points": int(len(tree.xyz)), "n_nodes": int(len(skel)), "n_branches": len(curves),
                 "bin_m": nodes["bin_m"], "spacing_k_m": nodes["spacing"],
                 "n_circle_fits": int(nodes["fitted"].sum()), "t_total_s": time.perf_counter() - t0}
        if nodes["spacing"] > 0.1:
            flags.append("sparse_scan")
        visited = float(nodes["n_used"]) / max(len(xyz), 1)
        rec = Reconstruction(skel, self.name, visited, nodes["n_bridges"] == 0, stats, flags, tree.tree_id)
        report(progress, 1.0, "model")
        dm = DenseModel(rec, None, None, curves, radii, bparent, border, cyl)
        if mesh_curves is not None:
            dm.mesh_curves, dm.mesh_radii = mesh_curves, mesh_radii
        dm.mesh_chord_m = self.chord_spacing * float(nodes["spacing"])
        return dm

    def reconstruct(self, tree: TreePoints, progress: Progress = None, cancelled: CancelCheck = None):
        return self.model(tree, progress, cancelled).reconstruction


def _voxel_thin(xyz: np.ndarray, target: int) -> np.ndarray:
    """One point (the first in file order) per cubic voxel, the voxel grown until at most ``target`` remain."""
    span = float(np.ptp(xyz, axis=0).max()) or 1.0
    size = 0.005
    while True:
        key = np.floor((xyz - xyz.min(axis=0)) / size).astype(np.int64)
        _, first = np.unique(key, axis=0, return_index=True)
        if len(first) <= target or size > span:
            return xyz[np.sort(first)]
        size *= 1.5


def _graph(xyz: np.ndarray, k: int):
    """Symmetric kNN graph (edge weights in metres), the median distance to the 8th neighbour, kNN arrays."""
    n = len(xyz)
    kk = min(k, n - 1)
    d, nb = cKDTree(xyz).query(xyz, k=kk + 1, workers=-1)
    spacing = float(np.median(d[:, min(8, kk)]))
    rows = np.repeat(np.arange(n), kk)
    g = sparse.csr_matrix((np.maximum(d[:, 1:].ravel(), 1e-9), (rows, nb[:, 1:].ravel())), shape=(n, n))
    return g.maximum(g.T).tocsr(), spacing


def _bridge(xyz: np.ndarray, g: sparse.csr_matrix, root: int, min_component: int):
    """Join the graph's pieces of at least ``min_component`` points to the piece holding ``root`` by their
    shortest link, nearest pieces first (Sylva: gaps left by occlusion); returns (graph, used mask, bridges)."""
    _, lab = csgraph.connected_components(g, directed=False)
    sizes = np.bincount(lab)
    used = sizes[lab] >= min_component
    used |= lab == lab[root]
    main = lab == lab[root]
    others = [c for c in np.unique(lab[used & ~main])]
    rows, cols, ws = [], [], []
    n_bridges = 0
    while others:
        tree = cKDTree(xyz[main])
        midx = np.flatnonzero(main)
        best = []
        for c in others:
            pts = np.flatnonzero(lab == c)
            d, j = tree.query(xyz[pts], workers=-1)
            i = int(np.argmin(d))
            best.append((float(d[i]), c, int(pts[i]), int(midx[j[i]])))
        best.sort()
        # attach every piece whose link is within twice the shortest one, then look again
        limit = 2 * best[0][0] + 1e-9
        for dist, c, a, b in best:
            if dist <= limit:
                rows += [a, b]
                cols += [b, a]
                ws += [max(dist, 1e-9)] * 2
                main |= lab == c
                n_bridges += 1
        others = [c for c in others if not main[np.flatnonzero(lab == c)[0]]]
    if rows:
        g = (g + sparse.csr_matrix((ws, (rows, cols)), shape=g.shape)).tocsr()
    return g, used, n_bridges


def level_set_nodes(xyz: np.ndarray, opt: LevelSetQSM = LevelSetQSM(), width=None, prep=None,
                    min_points: int = 1) -> dict:
    """The level-set nodes of a tree's points: centres, radii, parents (see the module docstring).

    ``width`` (n,) optional bin width per point (m): the geodesic distance is then measured in local
    bin widths (every edge's length divided by the mean width of its ends) and binned by 1, so bins are
    wide on thick stems and narrow on twigs.  ``prep`` the ``prep`` of an earlier call on the same points
    (graph, spacing, used mask, bridges).  ``min_points``: a node with exactly one child and fewer points
    (its own and those of the nodes already merged into it) joins its parent, tips first
    (:func:`_merge_thin_nodes`).  Returns a dict: ``centre`` (m, 3), ``radius`` (m,), ``parent``
    (m,) (-1 for the root, parents first), ``count`` points per node, ``tip`` (m, 3) the farthest point of
    each node along its axis, ``fitted`` (m,) True where a circle was fitted, ``label`` per point its node
    (-1 unused), and ``bin_m``, ``spacing``, ``n_used``, ``n_bridges``, ``prep``.
    """
    n = len(xyz)
    root = int(np.argmin(xyz[:, 2]))
    if prep is None:
        g, spacing = _graph(xyz, opt.k)
        g, used, n_bridges = _bridge(xyz, g, root, opt.min_component)
        prep = (g, spacing, used, n_bridges)
    g, spacing, used, n_bridges = prep
    if width is None:
        bin_m = opt.bin_m if opt.bin_m > 0 else float(np.clip(opt.bin_spacing * spacing, opt.min_bin_m,
                                                              opt.max_bin_m))
        gw, unit, src_m = g, bin_m, bin_m
    else:
        width = np.asarray(width, dtype=np.float64)
        coo = g.tocoo()
        gw = sparse.csr_matrix((coo.data / (0.5 * (width[coo.row] + width[coo.col])), (coo.row, coo.col)),
                               shape=g.shape)
        bin_m, unit, src_m = float(np.median(width)), 1.0, float(np.median(width))
    z0 = xyz[root, 2]
    src = np.flatnonzero(used & (xyz[:, 2] <= z0 + max(opt.root_m, src_m / 2)))
    dist, pred, _ = csgraph.dijkstra(gw, directed=False, indices=src, min_only=True, return_predecessors=True)
    dist = dist / unit
    bin_m_real = bin_m
    bin_m = 1.0
    reach = np.isfinite(dist) & used
    b = np.where(reach, np.floor(dist), -1).astype(np.int64)
    # pieces of each bin: components of the graph restricted to edges inside one bin
    # (the graph's edges, and links to the 16 nearest points within ``merge_spacing`` point spacings or a
    # bin: a thick stem cut into bins narrower than its point spacing stays one ring per bin)
    coo = g.tocoo()
    rows, cols = coo.row, coo.col
    if opt.merge_spacing > 0:
        kk = min(16, n - 1)
        _, nq = cKDTree(xyz).query(xyz, k=kk + 1, distance_upper_bound=max(opt.merge_spacing * spacing, bin_m_real),
                                   workers=-1)
        qi = np.repeat(np.arange(n), kk)
        qj = nq[:, 1:].ravel()
        live = qj < n
        rows = np.r_[rows, qi[live]]
        cols = np.r_[cols, qj[live]]
    same = (b[rows] == b[cols]) & (b[rows] >= 0)
    sub = sparse.csr_matrix((np.ones(same.sum()), (rows[same], cols[same])), shape=(n, n))
    _, comp = csgraph.connected_components(sub, directed=False)
    comp = np.where(reach, comp, -1)
    comp = _merge_split_sections(xyz, comp, b, dist)
    # relabel nodes by their smallest geodesic distance: parents (smaller distance) come first
    ok = comp >= 0
    ids, comp_r = np.unique(comp[ok], return_inverse=True)
    m = len(ids)
    lab = np.full(n, -1, dtype=np.int64)
    lab[ok] = comp_r
    first = _group_argmin(dist, lab, m)
    order = np.argsort(dist[first], kind="stable")
    rank = np.empty(m, dtype=np.int64)
    rank[order] = np.arange(m)
    lab[ok] = rank[lab[ok]]
    first = first[order]
    p = pred[first]
    parent = np.where(p >= 0, lab[np.maximum(p, 0)], -1)
    parent[parent >= np.arange(m)] = -1
    roots = np.flatnonzero(parent < 0)
    parent[roots[1:]] = roots[0]          # several pieces among the sources: all hang from the first
    cnt = np.bincount(lab[ok], minlength=m).astype(np.float64)
    if min_points > 1 and m > 1:
        target = _merge_thin_nodes(parent, cnt, float(min_points))
        kept = target == np.arange(m)
        new = np.cumsum(kept) - 1                 # kept nodes keep their order: parents still come first
        lab[ok] = new[target[lab[ok]]]
        parent = np.where(parent[kept] >= 0, new[target[np.maximum(parent[kept], 0)]], -1)
        m = int(kept.sum())
        cnt = np.bincount(lab[ok], minlength=m).astype(np.float64)
    centroid = np.stack([np.bincount(lab[ok], weights=xyz[ok, c], minlength=m) for c in range(3)], 1) / cnt[:, None]
    axis = _axes(centroid, parent)
    centre, radius, fitted = _fit_sections(xyz[ok], lab[ok], centroid, axis, m, opt.min_arc_deg)
    # the tip of a node: its farthest point along the axis (where the tube ends on a leaf node)
    proj = ((xyz[ok] - centre[lab[ok]]) * axis[lab[ok]]).sum(1)
    far = np.full(m, -np.inf)
    np.maximum.at(far, lab[ok], proj)
    tip = centre + axis * np.maximum(far, 0)[:, None]
    return dict(centre=centre, radius=radius, parent=parent, count=cnt, tip=tip, fitted=fitted, axis=axis,
                label=lab, z_min=float(z0), bin_m=bin_m_real, spacing=spacing, n_used=int(ok.sum()),
                n_bridges=n_bridges, prep=prep)


@njit
def _merge_thin_nodes(parent, cnt, least):
    """Per node the node it ends up in: a node with exactly one child and fewer than ``least`` points
    (its own and those already merged into it) joins its parent, tips first (parents come first, so a
    run of such nodes along a twig becomes nodes of at least ``least`` points); the forks and the tips
    stay.  Yan et al. (2009) §2.4 subdivide a cluster only while it holds more than a user-set number of
    points; here the fine level's bins, a quarter of the 8th-neighbour distance wide (narrower than the
    nearest-neighbour distance on a sparse scan: about one point per bin along a twig), are joined
    along a twig until a node holds that many, which on a surface of uniform spacing spans about the
    distance to its ``least``-th neighbour: the node's size follows the scan's spacing (Sylva, not in the
    paper).  Forks and tips are kept: a twig's last point is where its tube reaches, and leaving the tips
    out (or merging every small node) cost points -> surface on the TLS trees (benchmarks/dense.py).  With
    ``least`` 3: fine nodes of TLS trees 1 / 7 / 13: 4,379 / 3,562 / 3,406 -> 3,871 / 3,262 / 2,965."""
    m = parent.shape[0]
    c = cnt.copy()
    target = np.arange(m)
    kids = np.zeros(m, dtype=np.int64)
    for i in range(m):
        if parent[i] >= 0:
            kids[parent[i]] += 1
    for i in range(m - 1, 0, -1):
        p = parent[i]
        if p >= 0 and kids[i] == 1 and c[i] < least:
            target[i] = p
            c[p] += c[i]
            kids[p] += kids[i] - 1            # i's child now hangs from p
    for i in range(m):
        target[i] = target[target[i]]
    return target


def _group_argmin(values, labels, n):
    order = np.lexsort((values, labels))
    lab = labels[order]
    keep = lab >= 0
    order, lab = order[keep], lab[keep]
    starts = np.flatnonzero(np.r_[True, lab[1:] != lab[:-1]])
    out = np.zeros(n, dtype=np.int64)
    out[lab[starts]] = order[starts]
    return out


def _merge_split_sections(xyz, comp, b, dist):
    """Merge pieces of one bin whose centres are closer than the sum of their spreads (one cross-section
    seen in parts; Sylva, not in the papers)."""
    ok = comp >= 0
    if not ok.any():
        return comp
    ids, c = np.unique(comp[ok], return_inverse=True)
    m = len(ids)
    lab = np.full(len(comp), -1, dtype=np.int64)
    lab[ok] = c
    first = _group_argmin(dist, lab, m)
    cnt = np.bincount(c, minlength=m).astype(np.float64)
    cen = np.stack([np.bincount(c, weights=xyz[ok, k], minlength=m) for k in range(3)], 1) / cnt[:, None]
    spread = np.zeros(m)
    np.maximum.at(spread, c, np.linalg.norm(xyz[ok] - cen[c], axis=1))
    nb = b[first]
    key = np.argsort(nb, kind="stable")
    # candidate pairs: all pairs of pieces of one bin (whatever their parents: a thick stem cut by bins
    # narrower than its point spacing falls apart into arcs that each follow their own arc below)
    grp = np.r_[True, nb[key][1:] != nb[key][:-1]]
    starts = np.flatnonzero(grp)
    end_of = np.r_[starts[1:], m][np.cumsum(grp) - 1]       # per position in key order: its group's end
    after = end_of - np.arange(m) - 1                        # the pieces after it in its group
    i = np.repeat(np.arange(m), after)
    j = i + 1 + np.arange(len(i)) - np.repeat(np.cumsum(after) - after, after)
    a, b2 = key[i], key[j]
    close = np.linalg.norm(cen[a] - cen[b2], axis=1) < spread[a] + spread[b2]
    # joined pieces: connected components of the close pairs, each named by its smallest piece
    _, comp_of = csgraph.connected_components(
        sparse.csr_matrix((np.ones(int(close.sum())), (a[close], b2[close])), shape=(m, m)), directed=False)
    first_piece = np.full(m, m, dtype=np.int64)
    np.minimum.at(first_piece, comp_of, np.arange(m))
    roots = first_piece[comp_of]
    out = comp.copy()
    out[ok] = roots[c]
    return out


def _axes(centroid, parent):
    """Unit axis per node: from its parent's centre to the mean centre of its children (or to itself)."""
    m = len(centroid)
    child_sum = np.zeros((m, 3))
    n_child = np.zeros(m)
    has = parent >= 0
    np.add.at(child_sum, parent[has], centroid[has])
    np.add.at(n_child, parent[has], 1)
    below = np.where(has[:, None], centroid[np.maximum(parent, 0)], centroid)
    above = np.where(n_child[:, None] > 0, child_sum / np.maximum(n_child, 1)[:, None], centroid)
    v = above - below
    ln = np.linalg.norm(v, axis=1)
    v = np.where(ln[:, None] > 1e-9, v / np.maximum(ln, 1e-12)[:, None], np.array([0, 0, 1.0]))
    return v


def _fit_sections(pts, lab, centroid, axis, m, min_arc_deg, iterations=6):
    """(centre, radius, fitted) of every node: circle fit in the plane normal to its axis, else the median
    distance of its points to the axis through the centroid."""
    helper = np.where(np.abs(axis[:, 2:3]) < 0.9, np.array([0, 0, 1.0]), np.array([1.0, 0, 0]))
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(axis, e1)
    q = pts - centroid[lab]
    x, y = (q * e1[lab]).sum(1), (q * e2[lab]).sum(1)
    rho = np.hypot(x, y)
    cnt = np.bincount(lab, minlength=m).astype(np.float64)
    med = group_median(rho, lab, m)
    good = (cnt >= 8) & (arc_sectors(x, y, lab, m) >= 90)     # arc coverage around the centroid
    # the fit, its residual and the arc the points cover seen from the fitted centre
    cx, cy, r, rms, arc = fit_circles(x, y, lab, m, iterations=iterations, fit=good)
    spread = np.zeros(m)
    np.maximum.at(spread, lab, rho)
    good &= np.isfinite(r) & (r > 0) & (arc >= min_arc_deg) & (rms <= 0.25 * r + 0.005)
    good &= (np.hypot(cx, cy) <= 2.0 * np.maximum(spread, 1e-3)) & (r <= 2.0 * np.maximum(spread, 1e-3))
    centre = centroid + np.where(good[:, None], cx[:, None] * e1 + cy[:, None] * e2, 0.0)
    radius = np.where(good, r, np.where(np.isfinite(med), med, 0.0))
    radius = np.maximum(radius, 0.002)
    return centre, radius, good


@njit
def _best_child(parent, cnt):
    """Per node the child carrying the most points downstream (-1 for none); parents come first."""
    m = parent.shape[0]
    load = cnt.copy()
    for i in range(m - 1, 0, -1):
        if parent[i] >= 0:
            load[parent[i]] += load[i]
    best = np.full(m, -1, dtype=np.int64)
    best_load = np.full(m, -1.0)
    for i in range(m):
        p = parent[i]
        if p >= 0 and load[i] > best_load[p]:
            best[p] = i
            best_load[p] = load[i]
    return best


def _branches(nodes: dict, ground_z: float):
    """Branch centre lines and radii from the level-set nodes; the skeleton (base node first).

    A node continues into the child carrying the most points downstream; every other child starts a
    branch whose centre line begins at the parent's centre.  Radii: running median of three along a
    branch, a branch's first radius at most its parent's.  The trunk starts at the lowest stem points
    (the base, at the lowest point's height under the root's centre).  Leaf nodes end at their tip.
    """
    centre, radius, parent, cnt, tip = nodes["centre"], nodes["radius"].copy(), nodes["parent"], nodes["count"], nodes["tip"]
    m = len(centre)
    parent = np.asarray(parent, dtype=np.int64)
    best = _best_child(parent, cnt)
    chain_of, pos = _chain_ids(parent, best)
    nc = int(chain_of.max()) + 1 if m else 0
    order_nodes = np.lexsort((pos, chain_of))              # nodes chain by chain, base to tip
    lens = np.bincount(chain_of, minlength=nc)
    off = np.r_[0, np.cumsum(lens)]
    first, last = order_nodes[off[:-1]], order_nodes[off[1:] - 1]
    chain_parent = np.where(parent[first] >= 0, chain_of[np.maximum(parent[first], 0)], -1)
    # smooth radii along chains (running median of three, ends kept) and keep each branch's base no
    # thicker than its parent
    r = radius[order_nodes]
    cid = chain_of[order_nodes]
    inner = np.zeros(m, dtype=bool)
    if m > 2:
        inner[1:-1] = (cid[1:-1] == cid[:-2]) & (cid[1:-1] == cid[2:])
    i = np.flatnonzero(inner)
    a_, b_, c_ = r[i - 1], r[i], r[i + 1]
    sm = r.copy()
    sm[i] = np.maximum(np.minimum(a_, b_), np.minimum(np.maximum(a_, b_), c_))
    radius[order_nodes] = sm
    radius = _clamp_chains(radius, order_nodes, off, parent[first])
    base = np.array([centre[0, 0], centre[0, 1], min(nodes["z_min"], float(centre[0, 2]))])
    # centre lines: the parent's centre (or the base), the chain's centres, the last node's tip
    has_tip = np.linalg.norm(tip[last] - centre[last], axis=1) > 1e-3
    start = np.where((parent[first] >= 0)[:, None], centre[np.maximum(parent[first], 0)], base)
    n_out = lens + 1 + has_tip
    out_off = np.r_[0, np.cumsum(n_out)]
    pts = np.empty((int(out_off[-1]), 3))
    rad = np.empty(int(out_off[-1]))
    pts[out_off[:-1]] = start
    rad[out_off[:-1]] = radius[first]
    body = np.repeat(out_off[:-1] + 1 - off[:-1], lens) + np.arange(m)
    pts[body] = centre[order_nodes]
    rad[body] = radius[order_nodes]
    tp = out_off[1:][has_tip] - 1
    pts[tp] = tip[last[has_tip]]
    rad[tp] = radius[last[has_tip]]
    curves = np.split(pts, out_off[1:-1])
    radii = np.split(rad, out_off[1:-1])
    chains = np.split(order_nodes, off[1:-1])
    order = np.zeros(nc, dtype=np.int64)
    for c in range(nc):                    # parents' chains come first
        if chain_parent[c] >= 0:
            order[c] = order[chain_parent[c]] + 1
    # skeleton: the base, then the nodes (parents first, so node i + 1 has parent parent[i] + 1 or the base)
    sk_nodes = np.vstack([base, centre])
    sk_parent = np.r_[-1, np.where(parent >= 0, parent + 1, 0)]
    sk_radius = np.r_[radius[0], radius]
    skel = Skeleton(sk_nodes, sk_parent, sk_radius)
    return curves, radii, np.asarray(chain_parent, dtype=np.int64), order, skel, chains


@njit
def _chain_ids(parent, best):
    """Per node its chain (chains numbered by their first node) and its position in it; parents first."""
    m = parent.shape[0]
    chain = np.empty(m, dtype=np.int64)
    pos = np.empty(m, dtype=np.int64)
    n = 0
    for i in range(m):
        p = parent[i]
        if i == 0 or p < 0 or best[p] != i:
            chain[i] = n
            pos[i] = 0
            n += 1
        else:
            chain[i] = chain[p]
            pos[i] = pos[p] + 1
    return chain, pos


@njit
def _clamp_chains(radius, order_nodes, off, first_parent):
    """A chain whose first radius exceeds its parent node's is clamped to it, chains in order."""
    out = radius.copy()
    for c in range(off.shape[0] - 1):
        p = first_parent[c]
        if p < 0:
            continue
        cap = out[p]
        if out[order_nodes[off[c]]] > cap:
            for k in range(off[c], off[c + 1]):
                v = order_nodes[k]
                if out[v] > cap:
                    out[v] = cap
    return out


def prune_stubs(curves, radii, bparent, border, slack_m: float, factor: float = 3.0, passes: int = 3):
    """Branches without children that stay within ``factor`` parent radii + ``slack_m`` of the parent's
    centre line (a bump, or a second chain up the other side of the parent) are bumps of the parent's surface, not branches: left out of the structure
    (TreeQSM-like; Sylva, not in the papers).  Returns the kept (curves, radii, parents, orders)."""
    bp = np.asarray(bparent, dtype=np.int64).copy()
    keep = np.ones(len(curves), dtype=bool)
    for _ in range(passes):
        has_child = np.zeros(len(curves), dtype=bool)
        live = keep & (bp >= 0)
        has_child[bp[live]] = True
        drop = []
        for b in np.flatnonzero(keep & ~has_child & (bp >= 0)):
            # the farthest the branch gets from its parent's centre line (its vertices, densely sampled)
            par = curves[bp[b]]
            reach = float(np.min(np.linalg.norm(curves[b][:, None] - par[None], axis=2), axis=1).max())
            if reach <= factor * float(radii[bp[b]].max()) + slack_m:
                drop.append(b)
        if not drop:
            break
        keep[drop] = False
    idx = np.flatnonzero(keep)
    new = np.full(len(curves), -1, dtype=np.int64)
    new[idx] = np.arange(len(idx))
    return ([curves[i] for i in idx], [radii[i] for i in idx], np.where(bp[idx] >= 0, new[np.maximum(bp[idx], 0)], -1),
            np.asarray(border)[idx])
