"""The wood of a tree as a triangle mesh (Hu et al. 2017 §5.5): one closed tube per branch chain.

:func:`tree_mesh` / :func:`tree_mesh_arrays` smooth and sweep every chain, side branches starting on their
parent's axis; :class:`LevelOfDetail` (the standard levels :data:`LOD`, :data:`DEFAULT_LOD`) trades sides,
smoothing samples and pruned twigs.  The batch forms (:func:`tree_mesh_arrays_batch`, :func:`tree_meshes`,
:func:`forest_polylines`, :func:`forest_wood`) sweep the tubes of many trees at once and cut them back per
tree (compiled passes for the centre lines and the cut).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional, Union

import numpy as np

from ..errors import InputError
from ..jit import njit
from ..skeleton import Skeleton
from .branches import BranchSet, branches
from .passes import check_skeleton, join_forest
from .radii import radii_or_default
from .tubes import dedupe, hermite_batch, tube_batch


@dataclass(frozen=True)
class LevelOfDetail:
    """How finely :func:`tree_mesh` builds the wood.

    ``sides`` polygon sides of every tube; ``samples_per_segment`` Hermite
    samples per skeleton segment (1 = the skeleton polyline, no smoothing);
    ``min_radius_m`` branches whose base radius is below it are left out,
    with all branches they carry.
    """

    sides: int = 8
    samples_per_segment: int = 3
    min_radius_m: float = 0.0


#: The level of detail models get unless asked otherwise (light: a forest of them stays small).
DEFAULT_LOD = 0


#: The three standard levels: 0 coarse (4 sides, no smoothing, twigs under
#: 3 cm radius pruned), 1 middle, 2 fine (12 sides, 6 Hermite samples, all).
LOD = (
    LevelOfDetail(sides=4, samples_per_segment=1, min_radius_m=0.03),
    LevelOfDetail(sides=8, samples_per_segment=3, min_radius_m=0.01),
    LevelOfDetail(sides=12, samples_per_segment=6, min_radius_m=0.0),
)


def _lod(lod) -> LevelOfDetail:
    if isinstance(lod, LevelOfDetail):
        return lod
    try:
        return LOD[int(lod)]
    except (IndexError, ValueError, TypeError):
        raise InputError(f"lod must be 0, 1, 2 or a LevelOfDetail, got {lod!r}")


@dataclass
class TreeMeshParts:
    """The arrays of a tree's wood mesh before a trimesh is built.

    ``vertices`` (v, 3), ``faces`` (f, 3), ``face_branch`` (f,) the branch of
    each face (index into ``branches``), ``branches`` the decomposition used,
    ``kept`` (n_branches,) which branches were meshed.
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_branch: np.ndarray
    branches: BranchSet
    kept: np.ndarray


def tree_mesh_arrays(skeleton: Skeleton, lod: Union[int, LevelOfDetail] = DEFAULT_LOD,
                     radii: Optional[np.ndarray] = None, branch_set: Optional[BranchSet] = None) -> TreeMeshParts:
    """The wood of a tree as arrays: one closed generalised cylinder per branch.

    Radii come from ``radii``, else ``skeleton.radius`` if set, else the
    default pipe model.  Each branch chain (see :func:`branches`) is Hermite
    smoothed with ``lod.samples_per_segment`` and swept with ``lod.sides``;
    a side branch starts at its attachment node on the parent's axis with its
    own radius (so it starts inside the parent tube) and ends in a cap at its
    tip.  Branches with a base radius under ``lod.min_radius_m`` (and all
    they carry) are pruned; the trunk is always kept.  All tubes are built in
    one vectorised batch.  ``branch_set`` may pass ``branches(skeleton, radii)``
    when the caller has it already (it is not checked).
    """
    return tree_mesh_arrays_batch([skeleton], lod, None if radii is None else [radii],
                                  None if branch_set is None else [branch_set])[0]


@dataclass
class _Polylines:
    """The tube centre lines of a forest's trees before smoothing (see :func:`forest_polylines`).

    ``points``/``radii`` of all kept lines, ``lengths`` points per kept line, ``kept`` (n_branches,)
    which chains are meshed, ``line_off`` / ``point_off`` (n_trees + 1,) each tree's kept lines and
    their points, ``branch_off`` each tree's chains.
    """

    points: np.ndarray
    radii: np.ndarray
    lengths: np.ndarray
    kept: np.ndarray
    line_off: np.ndarray
    point_off: np.ndarray
    branch_off: np.ndarray


def forest_polylines(nodes: np.ndarray, radii: np.ndarray, bs: BranchSet, branch_off: np.ndarray,
                     lod: Union[int, LevelOfDetail]) -> _Polylines:
    """The tube centre lines of every tree of a forest (its BranchSet ``bs``, tree ``t`` owning chains
    ``branch_off[t]:branch_off[t + 1]``), as :func:`tree_mesh_arrays` builds them for each tree.

    A side branch starts with its own (child) radius at the attachment node; chains whose base
    radius is under ``lod.min_radius_m`` are pruned with all they carry, a tree's trunk never.
    """
    lod = _lod(lod)
    pts, r, lengths, kept, line_off = _polyline_kernel(
        np.ascontiguousarray(nodes, dtype=np.float64), np.ascontiguousarray(radii, dtype=np.float64), bs.nodes,
        bs.offsets, bs.parent, bs.attach, np.asarray(branch_off, dtype=np.int64), float(lod.min_radius_m))
    point_off = np.r_[0, np.cumsum(lengths)][line_off]
    return _Polylines(pts, r, lengths, kept, line_off, point_off, np.asarray(branch_off))


@njit
def _polyline_kernel(nodes, radii, chain, offsets, bparent, attach, branch_off, min_radius):
    """The kept chains' points and radii of :func:`forest_polylines` in one pass over the chains
    (parents before children): a chain is kept when its base radius (its own, for a side branch) is
    at least ``min_radius`` and its parent chain is kept, a tree's trunk always.  Returns (points,
    radii, points per kept chain, kept (n_branches,), kept chains per tree as offsets)."""
    nb = offsets.shape[0] - 1
    nt = branch_off.shape[0] - 1
    kept = np.zeros(nb, np.bool_)
    n_pts = 0
    n_lines = 0
    line_off = np.zeros(nt + 1, np.int64)
    for t in range(nt):
        for b in range(branch_off[t], branch_off[t + 1]):
            a, e = offsets[b], offsets[b + 1]
            first = a + 1 if attach[b] >= 0 and e - a > 1 else a      # a side branch starts with its own radius
            keep = b == branch_off[t] or radii[chain[first]] >= min_radius
            if bparent[b] >= 0:
                keep = keep and kept[bparent[b]]
            kept[b] = keep
            if keep:
                n_pts += e - a
                n_lines += 1
        line_off[t + 1] = n_lines
    pts = np.empty((n_pts, 3))
    r = np.empty(n_pts)
    lengths = np.empty(n_lines, np.int64)
    k = 0
    line = 0
    for b in range(nb):
        if kept[b]:
            a, e = offsets[b], offsets[b + 1]
            lengths[line] = e - a
            line += 1
            for j in range(a, e):
                for c in range(3):
                    pts[k, c] = nodes[chain[j], c]
                r[k] = radii[chain[j]]
                k += 1
            if attach[b] >= 0 and e - a > 1:
                r[k - (e - a)] = radii[chain[a + 1]]
    return pts, r, lengths, kept, line_off


def _forest_wood_arrays(lines: _Polylines, a: int, b: int, lod: Union[int, LevelOfDetail]) -> list:
    """(vertices, faces, face branch) of the wood of trees ``a:b`` of :func:`forest_polylines`, swept in one batch."""
    lod = _lod(lod)
    l0, l1 = lines.line_off[a], lines.line_off[b]
    p0, p1 = lines.point_off[a], lines.point_off[b]
    lines_per_tree = np.diff(lines.line_off[a:b + 1])
    kept = [np.flatnonzero(lines.kept[b0:b1]) for b0, b1 in
            zip(lines.branch_off[a:b].tolist(), lines.branch_off[a + 1:b + 1].tolist())]
    if l1 == l0:
        e = np.zeros(0, dtype=np.int64)
        return [(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), e) for _ in range(b - a)]
    offsets = np.r_[0, np.cumsum(lines.lengths[l0:l1])].astype(np.int64)
    pts, r, offsets, _ = dedupe(lines.points[p0:p1], lines.radii[p0:p1], offsets)
    pts, r, offsets = hermite_batch(pts, r, offsets, lod.samples_per_segment)
    verts, faces, face_line = tube_batch(pts, r, offsets, lod.sides, cap=True)
    if b - a == 1:
        groups = [(verts, faces, face_line)]
    else:
        groups = _split_tube_batch(verts, faces, face_line, offsets, lines_per_tree, lod.sides)
    return [(v, f, k[fl]) for (v, f, fl), k in zip(groups, kept)]


def forest_wood(lines: _Polylines, a: int, b: int, lod: Union[int, LevelOfDetail]) -> list:
    """:func:`tree_meshes` of trees ``a:b`` of :func:`forest_polylines` (one trimesh each)."""
    import trimesh

    out = []
    for v, f, fb in _forest_wood_arrays(lines, a, b, lod):
        mesh = trimesh.Trimesh(v, f, process=False)
        mesh.metadata["face_branch"] = fb
        out.append(mesh)
    return out


def _join_branch_sets(bsets: List[BranchSet], node_off: np.ndarray):
    """One forest BranchSet of per-tree BranchSets (trees = node ranges ``node_off``) and its branch offsets."""
    nb = np.array([len(bs) for bs in bsets], dtype=np.int64)
    boff = np.r_[0, np.cumsum(nb)]
    coff = np.r_[0, np.cumsum([len(bs.nodes) for bs in bsets])].astype(np.int64)
    n0, b0, c0 = node_off[:-1].tolist(), boff[:-1].tolist(), coff[:-1].tolist()

    def cat(arrays):
        return np.concatenate(arrays).astype(np.int64) if arrays else np.zeros(0, dtype=np.int64)

    def shift(x, d):
        return np.where(x >= 0, x + d, -1)

    nodes = cat([bs.nodes + n for bs, n in zip(bsets, n0)])
    offsets = cat([bs.offsets[:-1] + c for bs, c in zip(bsets, c0)] + [coff[-1:]])
    joined = BranchSet(nodes, offsets, cat([shift(bs.parent, b) for bs, b in zip(bsets, b0)]),
                       cat([shift(bs.attach, n) for bs, n in zip(bsets, n0)]),
                       cat([bs.node_branch + b for bs, b in zip(bsets, b0)]), cat([bs.order for bs in bsets]),
                       cat([shift(bs.continuation, n) for bs, n in zip(bsets, n0)]))
    return joined, boff


def tree_mesh_arrays_batch(skeletons, lod: Union[int, LevelOfDetail] = DEFAULT_LOD, radii=None,
                           branch_sets=None) -> List[TreeMeshParts]:
    """:func:`tree_mesh_arrays` of many trees, with the tubes of all of them swept in one batch.

    ``radii`` and ``branch_sets`` are None or one entry (array or None) per skeleton.  Every
    step of the sweep works point by point along each polyline, so each tree gets exactly the
    arrays (same values, vertex and face order) a call for it alone gives.
    """
    lod = _lod(lod)
    skeletons = [check_skeleton(sk) for sk in skeletons]
    nt = len(skeletons)
    if nt == 0:
        return []
    radii = [None] * nt if radii is None else list(radii)
    branch_sets = [None] * nt if branch_sets is None else list(branch_sets)
    rad = [radii_or_default(sk, r) for sk, r in zip(skeletons, radii)]
    bsets = [bs if bs is not None else branches(sk, r) for sk, r, bs in zip(skeletons, rad, branch_sets)]
    nodes, _, off = join_forest(skeletons)
    joined, boff = _join_branch_sets(bsets, off)
    lines = forest_polylines(nodes, np.concatenate(rad), joined, boff, lod)
    return [TreeMeshParts(v, f, fb, bs, lines.kept[b0:b1])
            for (v, f, fb), bs, b0, b1 in zip(_forest_wood_arrays(lines, 0, nt, lod), bsets,
                                              boff[:-1].tolist(), boff[1:].tolist())]


def _split_tube_batch(verts, faces, face_line, offsets, lines_per_tree, sides):
    """Per tree (vertices, faces, face line within the tree) of a :func:`tube_batch` over many trees.

    Reorders the vertices into the layout a batch of that tree alone has (ring corner ``j`` of
    point ``i`` at ``j * n + i``, then the first caps, then the last caps) and keeps the faces
    in their batch order, which is the order of the tree alone.
    """
    line_off = np.r_[0, np.cumsum(lines_per_tree)].astype(np.int64)
    out_v, out_f, out_l, v_off, f_off = _split_tube_kernel(
        np.ascontiguousarray(verts, dtype=np.float64), np.ascontiguousarray(faces, dtype=np.int64),
        np.ascontiguousarray(face_line, dtype=np.int64), np.asarray(offsets, dtype=np.int64), line_off, int(sides))
    vb, fb = v_off.tolist(), f_off.tolist()
    return [(out_v[vb[t]:vb[t + 1]], out_f[fb[t]:fb[t + 1]], out_l[fb[t]:fb[t + 1]])
            for t in range(len(lines_per_tree))]


@njit
def _split_tube_kernel(verts, faces, face_line, offsets, line_off, sides):
    """The reordering of :func:`_split_tube_batch` in one pass over points, caps and faces (a stable
    counting sort of the faces by tree); returns (vertices, faces, face lines, vertex and face offsets)."""
    n = offsets[offsets.shape[0] - 1]
    nt = line_off.shape[0] - 1
    nl = offsets.shape[0] - 1
    tree_of_line = np.empty(nl, np.int64)
    for t in range(nt):
        for line in range(line_off[t], line_off[t + 1]):
            tree_of_line[line] = t
    nb = 0
    for line in range(nl):
        if offsets[line + 1] - offsets[line] >= 2:
            nb += 1
    n_t = np.zeros(nt, np.int64)           # points and capped lines of every tree
    c_t = np.zeros(nt, np.int64)
    for line in range(nl):
        t = tree_of_line[line]
        n_t[t] += offsets[line + 1] - offsets[line]
        if offsets[line + 1] - offsets[line] >= 2:
            c_t[t] += 1
    v_off = np.zeros(nt + 1, np.int64)
    for t in range(nt):
        v_off[t + 1] = v_off[t] + n_t[t] * sides + 2 * c_t[t]
    new = np.empty(verts.shape[0], np.int64)
    cap = 0
    for t in range(nt):
        p0 = offsets[line_off[t]]
        base = v_off[t] + n_t[t] * sides
        c0 = cap
        for line in range(line_off[t], line_off[t + 1]):
            for i in range(offsets[line], offsets[line + 1]):
                for j in range(sides):
                    new[j * n + i] = v_off[t] + j * n_t[t] + (i - p0)
            if offsets[line + 1] - offsets[line] >= 2:
                new[n * sides + cap] = base + (cap - c0)
                new[n * sides + nb + cap] = base + c_t[t] + (cap - c0)
                cap += 1
    out_v = np.empty_like(verts)
    for v in range(verts.shape[0]):
        for c in range(3):
            out_v[new[v], c] = verts[v, c]
    nf = faces.shape[0]
    f_off = np.zeros(nt + 1, np.int64)
    for f in range(nf):
        f_off[tree_of_line[face_line[f]] + 1] += 1
    for t in range(nt):
        f_off[t + 1] += f_off[t]
    fill = f_off[:nt].copy()
    out_f = np.empty((nf, 3), np.int64)
    out_l = np.empty(nf, np.int64)
    for f in range(nf):
        t = tree_of_line[face_line[f]]
        pos = fill[t]
        fill[t] += 1
        for c in range(3):
            out_f[pos, c] = new[faces[f, c]] - v_off[t]
        out_l[pos] = face_line[f] - line_off[t]
    return out_v, out_f, out_l, v_off, f_off


def tree_mesh(skeleton: Skeleton, lod: Union[int, LevelOfDetail] = DEFAULT_LOD,
              radii: Optional[np.ndarray] = None, per_branch: bool = False,
              branch_set: Optional[BranchSet] = None):
    """The wood of a tree as a :class:`trimesh.Trimesh` (see :func:`tree_mesh_arrays`).

    One mesh holding all branch tubes (each tube is closed; they overlap at
    the joints and are not boolean-merged), built once with ``process=False``;
    ``mesh.metadata["face_branch"]`` gives the branch of each face.  With
    ``per_branch=True`` returns a list of one watertight mesh per meshed branch.
    ``branch_set``: see :func:`tree_mesh_arrays`.
    """
    import trimesh

    parts = tree_mesh_arrays(skeleton, lod, radii, branch_set)
    if not per_branch:
        mesh = trimesh.Trimesh(parts.vertices, parts.faces, process=False)
        mesh.metadata["face_branch"] = parts.face_branch
        return mesh
    out = []
    for b in np.flatnonzero(parts.kept):
        f = parts.faces[parts.face_branch == b]
        if len(f) == 0:
            continue
        used, inv = np.unique(f, return_inverse=True)
        out.append(trimesh.Trimesh(parts.vertices[used], inv.reshape(-1, 3), process=False))
    return out


def tree_meshes(skeletons, lod: Union[int, LevelOfDetail] = DEFAULT_LOD, radii=None, branch_sets=None) -> list:
    """:func:`tree_mesh` of many trees (one :class:`trimesh.Trimesh` each), the tubes swept in one batch.

    The same meshes as one :func:`tree_mesh` call per tree (see :func:`tree_mesh_arrays_batch`).
    """
    import trimesh

    out = []
    for parts in tree_mesh_arrays_batch(skeletons, lod, radii, branch_sets):
        mesh = trimesh.Trimesh(parts.vertices, parts.faces, process=False)
        mesh.metadata["face_branch"] = parts.face_branch
        out.append(mesh)
    return out
