"""Leaves at branch tips by phyllotaxis: leaf cards and conifer needle clusters.

Hu et al. 2017 §5.6 ("Leaf arrangement"): the airborne points cannot show
leaves, so leaves are arranged on the branch tips by botanical rules — three
phyllotaxis patterns, *distichy*, *dispersion* and *decussation* — on the
last segments of each branch: for a branch of nodes ``s_1 .. s_n`` the
segments ``(s_j, s_j+1) .. (s_n-1, s_n)`` with ``n - 3 <= j <= n - 1``
(``tip_segments = 3``).  Successive leaves turn around the twig by

* ``"distichy"``    180° (alternate leaves in two rows, one plane);
* ``"dispersion"``  the golden angle 137.5° (spiral phyllotaxis);
* ``"decussation"`` opposite pairs (180° within a pair), successive pairs
  turned by 90°.

Each leaf is a *leaf card* (Guo et al. 2018 §5.2: "quads with alpha
textures"): one quad of two triangles with texture coordinates, whose long
axis leaves the twig at ``insertion_angle_deg`` in the phyllotaxis direction;
:class:`NeedleClusters` instead places pairs of crossed quads textured with a
needle spray (the usual conifer billboard).  Azimuths, insertion angles, roll
and size get seeded random jitter.  Textures come from
:func:`sylva.core.textures.leaf_texture` (drawn by Sylva, never copied).

All tips and leaves of a tree, or of many trees at once (:func:`grow_leaves_batch`,
same result per tree), are built in one compiled pass (angles and random draws by
numpy).  Cards are single-sided quads: render them with a double-sided,
alpha-masked material.
Texture coordinates follow the OBJ/OpenGL convention (v = 0 at the petiole,
the bottom row of the image; glTF writers flip v).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional, Union

import numpy as np

from .errors import InputError
from .geometry import branches, join_forest, norm3
from .jit import njit
from .skeleton import Skeleton
from .textures import leaf_aspect, leaf_texture, leaf_shape_name

__all__ = ["PATTERNS", "GOLDEN_ANGLE_DEG", "phyllotaxis_azimuths", "LeafCards", "NeedleClusters",
           "LeafMesh", "grow_leaves", "grow_leaves_batch", "forest_tip_sections", "leaves_at_tips", "leaf_cards",
           "needle_clusters", "leaf_texture"]

#: The golden angle 180° (3 - sqrt 5) = 137.5077...°, the divergence of spiral phyllotaxis.
GOLDEN_ANGLE_DEG = float(180.0 * (3.0 - np.sqrt(5.0)))
PATTERNS = ("distichy", "dispersion", "decussation")


def phyllotaxis_azimuths(pattern: str, n: int):
    """Azimuths (degrees, around the twig) and leaf-node ranks of ``n`` leaves.

    ``distichy``: 0, 180, 360, ... one leaf per node; ``dispersion``: k times
    the golden angle, one leaf per node; ``decussation``: two opposite leaves
    per node (0 and 180), successive nodes turned by 90°.  Returns
    ``(azimuth_deg (n,), node (n,) int)``.
    """
    k = np.arange(int(n))
    if pattern == "distichy":
        return 180.0 * k, k
    if pattern == "dispersion":
        return GOLDEN_ANGLE_DEG * k, k
    if pattern == "decussation":
        return 90.0 * (k // 2) + 180.0 * (k % 2), k // 2
    raise InputError(f"unknown phyllotaxis pattern {pattern!r}: use one of {', '.join(PATTERNS)}")


@dataclass(frozen=True)
class LeafCards:
    """Broadleaf cards at branch tips (Hu et al. 2017 §5.6).

    ``pattern`` phyllotaxis (distichy, dispersion, decussation);
    ``shape`` leaf texture (ovate, lobed, palmate, lanceolate, deltoid, or a
    species such as apple, cherry, maple, poplar); ``leaves_per_tip`` leaves
    on the last ``tip_segments`` segments of every branch (3 in the paper);
    ``leaf_length_m`` card length including the petiole, ``leaf_width_m``
    card width (default: length times the texture's aspect);
    ``insertion_angle_deg`` angle between the twig and the leaf axis;
    ``face_up`` 0..1, how far the blade turns towards horizontal (leaves face
    the light); jitter: ``azimuth_jitter_deg``, ``angle_jitter_deg``,
    ``roll_jitter_deg`` (standard deviations) and ``size_jitter`` (relative).
    """

    pattern: str = "dispersion"
    shape: str = "ovate"
    leaves_per_tip: int = 12
    tip_segments: int = 3
    leaf_length_m: float = 0.10
    leaf_width_m: Optional[float] = None
    insertion_angle_deg: float = 50.0
    face_up: float = 0.6
    azimuth_jitter_deg: float = 8.0
    angle_jitter_deg: float = 8.0
    roll_jitter_deg: float = 10.0
    size_jitter: float = 0.15
    crossed: bool = False


@dataclass(frozen=True)
class NeedleClusters:
    """Conifer needle clusters: crossed quads with a needle-spray texture along the tips.

    Same placement as :class:`LeafCards` (phyllotaxis on the last
    ``tip_segments`` segments); each cluster is two quads crossed at 90°
    around an axis leaving the twig at ``insertion_angle_deg``.
    """

    pattern: str = "dispersion"
    shape: str = "needle_spray"
    clusters_per_tip: int = 8
    tip_segments: int = 3
    cluster_length_m: float = 0.30
    cluster_width_m: Optional[float] = None
    insertion_angle_deg: float = 30.0
    face_up: float = 0.0
    azimuth_jitter_deg: float = 12.0
    angle_jitter_deg: float = 8.0
    roll_jitter_deg: float = 0.0
    size_jitter: float = 0.2
    crossed: bool = True


@dataclass
class LeafMesh:
    """Leaf cards of one tree as arrays.

    ``vertices`` (4 c, 3) metres, ``faces`` (2 c, 3), ``uvs`` (4 c, 2) for
    ``c`` cards (one per leaf, two per needle cluster); ``texture`` the leaf
    shape (see :func:`sylva.core.textures.leaf_texture`), ``material`` a
    material name.  Per leaf: ``tip`` the tip node it grows below, ``base``
    (n, 3) the attachment point, ``axis`` (n, 3) unit leaf axis, ``twig``
    (n, 3) unit twig direction, ``azimuth_deg`` the phyllotaxis azimuth
    (jitter included) around the twig and ``node`` the leaf's node rank.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray
    texture: str
    material: str
    tip: np.ndarray
    base: np.ndarray
    axis: np.ndarray
    twig: np.ndarray
    azimuth_deg: np.ndarray
    node: np.ndarray
    extras: dict = field(default_factory=dict)

    @property
    def n_leaves(self) -> int:
        return len(self.tip)

    def texture_image(self, size: int = 256) -> np.ndarray:
        """The RGBA texture of these cards."""
        return leaf_texture(self.texture, size)

    def to_trimesh(self, texture_size: int = 256):
        """A :class:`trimesh.Trimesh` with UVs (and the texture image when Pillow is installed)."""
        import trimesh

        mesh = trimesh.Trimesh(self.vertices, self.faces, process=False)
        try:
            from PIL import Image

            image = Image.fromarray(self.texture_image(texture_size), "RGBA")
            material = trimesh.visual.material.SimpleMaterial(image=image, name=self.material)
            mesh.visual = trimesh.visual.TextureVisuals(uv=self.uvs, material=material)
        except ImportError:
            mesh.visual = trimesh.visual.TextureVisuals(uv=self.uvs)
        return mesh


@njit
def _leaf_kernel(nodes, radii, sect, live, seglen, total, frac, cphi, sphi, cia, sia, cro, sro, scale, face_up,
                 length_m, half_w_m, crossed, card0, dir_step):
    """The leaves of the tip sections ``sect[live]`` (Hu et al. 2017 §5.6, see :func:`grow_leaves`) given
    the trigonometry of their angles; plain loops for numba.

    Per tip ``i``: the unit directions of its K segments (a zero-length one takes the next), the
    reference normal (horizontal at the first segment, carried along by minimal rotations); per leaf
    ``j`` its segment, position, twig frame, radial and blade directions (rolled, turned to face
    up), base point and card corners.  ``seglen`` / ``total`` are numpy's segment lengths and their
    sums, ``cphi``/``sphi`` cos/sin of the azimuths, ``cia``/``sia`` of the insertion angles,
    ``cro``/``sro`` of the roll (numpy's too).  Every expression is written in the order numpy
    evaluates the same vector expression (cross products a1 b2 - a2 b1, ..., dot products
    0 + x + y + z); tests/test_forest_invariants.py guards the leaves (golden outputs, batch equals
    one tree at a time).  Returns base, axis, twig (t, L, 3) and the card corners (cards, 4, 3):
    leaf ``j`` of tip ``i`` in direction ``e`` (two crossed ones, or one) is card
    ``card0[i] + e * dir_step[i] + j``.
    """
    nt, K = live.shape[0], seglen.shape[1]
    L = frac.shape[0]
    ncross = 2 if crossed else 1
    base = np.empty((nt, L, 3))
    axis = np.empty((nt, L, 3))
    twig = np.empty((nt, L, 3))
    corners = np.empty((ncross * nt * L, 4, 3))
    d = np.empty((K, 3))
    ref = np.empty((K, 3))
    seg = np.empty((K, 3))
    cum = np.zeros(K + 1)
    w = np.empty((2, 3))
    for i in range(nt):
        tip = live[i]
        for q in range(K):
            for c in range(3):
                seg[q, c] = nodes[sect[tip, q + 1], c] - nodes[sect[tip, q], c]
            n = seglen[tip, q] if seglen[tip, q] > 0 else 1.0
            for c in range(3):
                d[q, c] = seg[q, c] / n
            cum[q + 1] = seglen[tip, q] if q == 0 else cum[q] + seglen[tip, q]      # np.cumsum
        for q in range(K - 2, -1, -1):
            if seglen[tip, q] <= 0:
                for c in range(3):
                    d[q, c] = d[q + 1, c]
        # horizontal normal z x d, or y x d when d is vertical
        r0 = 0.0 * d[0, 2] - 1.0 * d[0, 1]
        r1 = 1.0 * d[0, 0] - 0.0 * d[0, 2]
        r2 = 0.0 * d[0, 1] - 0.0 * d[0, 0]
        if math.sqrt(r0 * r0 + r1 * r1 + r2 * r2) < 1e-6:
            r0 = 1.0 * d[0, 2] - 0.0 * d[0, 1]
            r1 = 0.0 * d[0, 0] - 0.0 * d[0, 2]
            r2 = 0.0 * d[0, 1] - 1.0 * d[0, 0]
        n = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        n = n if n > 0 else 1.0
        ref[0, 0], ref[0, 1], ref[0, 2] = r0 / n, r1 / n, r2 / n
        for q in range(1, K):
            # minimal rotation taking d[q - 1] to d[q], applied to ref[q - 1]
            a0, a1, a2 = d[q - 1, 0], d[q - 1, 1], d[q - 1, 2]
            b0, b1, b2 = d[q, 0], d[q, 1], d[q, 2]
            v0, v1, v2 = ref[q - 1, 0], ref[q - 1, 1], ref[q - 1, 2]
            cq = 0.0 + a0 * b0 + a1 * b1 + a2 * b2
            if cq > -0.999999:
                k0 = a1 * b2 - a2 * b1
                k1 = a2 * b0 - a0 * b2
                k2 = a0 * b1 - a1 * b0
                f = (0.0 + k0 * v0 + k1 * v1 + k2 * v2) / (1.0 + cq)
                u0 = v0 * cq + (k1 * v2 - k2 * v1) + k0 * f
                u1 = v1 * cq + (k2 * v0 - k0 * v2) + k1 * f
                u2 = v2 * cq + (k0 * v1 - k1 * v0) + k2 * f
            else:
                u0, u1, u2 = v0, v1, v2
            n = math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
            n = n if n > 0 else 1.0
            ref[q, 0], ref[q, 1], ref[q, 2] = u0 / n, u1 / n, u2 / n
        for j in range(L):
            s = total[tip] * frac[j]
            q = 0
            for e in range(1, K):
                if cum[e] <= s:
                    q += 1
            q = min(max(q, 0), K - 1)
            loc = (s - cum[q]) / (seglen[tip, q] if seglen[tip, q] > 0 else 1.0)
            t0, t1, t2 = d[q, 0], d[q, 1], d[q, 2]
            g = 0.0 + ref[q, 0] * t0 + ref[q, 1] * t1 + ref[q, 2] * t2
            x0, x1, x2 = ref[q, 0] - g * t0, ref[q, 1] - g * t1, ref[q, 2] - g * t2
            n = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
            n = n if n > 0 else 1.0
            x0, x1, x2 = x0 / n, x1 / n, x2 / n
            y0 = t1 * x2 - t2 * x1                       # s = twig x r
            y1 = t2 * x0 - t0 * x2
            y2 = t0 * x1 - t1 * x0
            rad_at = radii[sect[tip, q]] + loc * (radii[sect[tip, q + 1]] - radii[sect[tip, q]])
            cp, sp = cphi[i, j], sphi[i, j]
            o0, o1, o2 = cp * x0 + sp * y0, cp * x1 + sp * y1, cp * x2 + sp * y2       # radial direction
            w0, w1, w2 = -sp * x0 + cp * y0, -sp * x1 + cp * y1, -sp * x2 + cp * y2    # across the blade
            ci, si = cia[i, j], sia[i, j]
            ax0, ax1, ax2 = ci * t0 + si * o0, ci * t1 + si * o1, ci * t2 + si * o2
            cr, sr = cro[i, j], sro[i, j]
            z0 = ax1 * w2 - ax2 * w1
            z1 = ax2 * w0 - ax0 * w2
            z2 = ax0 * w1 - ax1 * w0
            w0, w1, w2 = cr * w0 + sr * z0, cr * w1 + sr * z1, cr * w2 + sr * z2
            if face_up > 0:
                h0 = ax1 * 1.0 - ax2 * 0.0               # axis x up
                h1 = ax2 * 0.0 - ax0 * 1.0
                h2 = ax0 * 0.0 - ax1 * 0.0
                hn = math.sqrt(h0 * h0 + h1 * h1 + h2 * h2)
                if hn > 1e-6:
                    hd = hn if hn > 0 else 1.0
                    h0, h1, h2 = h0 / hd, h1 / hd, h2 / hd
                else:
                    h0, h1, h2 = w0, w1, w2
                sg = 0.0 + h0 * w0 + h1 * w1 + h2 * w2 + 1e-12
                sg = 1.0 if sg > 0 else (-1.0 if sg < 0 else (0.0 if sg == 0 else sg))    # np.sign
                h0, h1, h2 = h0 * sg, h1 * sg, h2 * sg
                w0 = (1.0 - face_up) * w0 + face_up * h0
                w1 = (1.0 - face_up) * w1 + face_up * h1
                w2 = (1.0 - face_up) * w2 + face_up * h2
                g = 0.0 + w0 * ax0 + w1 * ax1 + w2 * ax2
                w0, w1, w2 = w0 - g * ax0, w1 - g * ax1, w2 - g * ax2
                n = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
                n = n if n > 0 else 1.0
                w0, w1, w2 = w0 / n, w1 / n, w2 / n
            p0 = nodes[sect[tip, q], 0] + loc * seg[q, 0]
            p1 = nodes[sect[tip, q], 1] + loc * seg[q, 1]
            p2 = nodes[sect[tip, q], 2] + loc * seg[q, 2]
            base[i, j, 0], base[i, j, 1], base[i, j, 2] = p0 + rad_at * o0, p1 + rad_at * o1, p2 + rad_at * o2
            axis[i, j, 0], axis[i, j, 1], axis[i, j, 2] = ax0, ax1, ax2
            twig[i, j, 0], twig[i, j, 1], twig[i, j, 2] = t0, t1, t2
            length = length_m * scale[i, j]
            hw = half_w_m * scale[i, j]
            w[0, 0], w[0, 1], w[0, 2] = w0, w1, w2
            w[1, 0] = ax1 * w2 - ax2 * w1
            w[1, 1] = ax2 * w0 - ax0 * w2
            w[1, 2] = ax0 * w1 - ax1 * w0
            for e in range(ncross):
                card = card0[i] + e * dir_step[i] + j
                for c in range(3):
                    b_ = base[i, j, c]
                    tp = b_ + length * axis[i, j, c]
                    corners[card, 0, c] = b_ - hw * w[e, c]
                    corners[card, 1, c] = b_ + hw * w[e, c]
                    corners[card, 2, c] = tp + hw * w[e, c]
                    corners[card, 3, c] = tp - hw * w[e, c]
    return base, axis, twig, corners




def _tip_sections(skeleton: Skeleton, tip_segments: int, branch_set=None):
    """Node indices (t, K + 1) of the last K segments of every branch (padded at the start)."""
    bset = branch_set if branch_set is not None else branches(skeleton)
    return _chain_tips(bset.nodes, bset.offsets, tip_segments)


def _chain_tips(nodes: np.ndarray, offsets: np.ndarray, tip_segments: int) -> np.ndarray:
    """The last ``tip_segments`` segments (t, K + 1) of every chain of two or more nodes of a BranchSet's arrays."""
    real = np.flatnonzero(np.diff(offsets) >= 2)
    if len(real) == 0:
        return np.zeros((0, tip_segments + 1), dtype=np.int64)
    ends, starts = offsets[real + 1], offsets[real]
    k = np.arange(tip_segments + 1)[None, :]
    pos = ends[:, None] - 1 - (tip_segments - k)
    pos = np.maximum(pos, starts[:, None])
    return nodes[pos]


def forest_tip_sections(bs, branch_off: np.ndarray, tip_segments: int):
    """:func:`_tip_sections` of every tree of a forest's BranchSet (global node indices) and the tree of each."""
    sect = _chain_tips(bs.nodes, bs.offsets, tip_segments)
    tree_of_branch = np.repeat(np.arange(len(branch_off) - 1), np.diff(branch_off))
    return sect, tree_of_branch[np.diff(bs.offsets) >= 2]


def grow_leaves(skeleton: Skeleton, method: Union[LeafCards, NeedleClusters] = LeafCards(),
                seed: int = 0, radii: Optional[np.ndarray] = None, branch_set=None) -> LeafMesh:
    """Leaf cards (or needle clusters) on the branch tips of ``skeleton``, Hu et al. 2017 §5.6.

    For every branch chain (see :func:`sylva.core.geometry.branches`) the
    last ``method.tip_segments`` segments carry ``leaves_per_tip`` leaves
    (``clusters_per_tip`` for needles) at evenly spaced leaf nodes along their
    length (one leaf per node, two for decussation); azimuths follow
    :func:`phyllotaxis_azimuths`, measured from a horizontal reference carried
    along the twig by minimal rotations (so bends do not twist the pattern).
    Distichous rows start horizontal; the other patterns start at a random
    azimuth per tip.  Leaves attach at the twig surface (``radii``, default
    ``skeleton.radius``).  Deterministic for a given ``seed``.  ``branch_set``
    may pass ``branches(skeleton)`` (no radii) when the caller has it already.
    """
    return grow_leaves_batch([skeleton], method, [seed], None if radii is None else [radii],
                             None if branch_set is None else [branch_set])[0]


def grow_leaves_batch(skeletons, method: Union[LeafCards, NeedleClusters] = LeafCards(), seeds=None,
                      radii=None, branch_sets=None) -> list:
    """:func:`grow_leaves` of many trees with one method, all tips computed in one vectorised pass.

    ``seeds`` one seed per skeleton (default 0 each); ``radii`` and ``branch_sets`` None or one
    entry (array or None) per skeleton.  Each tree draws its random numbers from its own
    generator in the order a call for it alone does, and every other step works tip by tip,
    so each tree gets exactly the :class:`LeafMesh` of ``grow_leaves(skeleton, method, seed)``.
    """
    skeletons = list(skeletons)
    ntree = len(skeletons)
    for skeleton in skeletons:
        if not isinstance(skeleton, Skeleton):
            raise InputError(f"expected a Skeleton, got {type(skeleton).__name__}")
    if not isinstance(method, (LeafCards, NeedleClusters)):
        raise InputError(f"unknown leaf method {method!r}: use LeafCards(...) or NeedleClusters(...)")
    seeds = [0] * ntree if seeds is None else list(seeds)
    radii = [None] * ntree if radii is None else list(radii)
    branch_sets = [None] * ntree if branch_sets is None else list(branch_sets)
    needles, per_tip, length_m, width_m, shape, ksegs = _leaf_sizes(method)
    if per_tip < 0 or ksegs < 1 or not (length_m > 0) or not (width_m > 0):
        raise InputError("leaves: need leaves_per_tip >= 0, tip_segments >= 1 and positive leaf sizes "
                         f"(got {per_tip}, {ksegs}, {length_m} m, {width_m} m)")
    sects, tip_tree, rad_all = [], [], []
    for t, (skeleton, r, bs) in enumerate(zip(skeletons, radii, branch_sets)):
        rad = skeleton.radius if r is None else np.asarray(r, dtype=np.float64).reshape(-1)
        if len(rad) != len(skeleton):
            raise InputError(f"leaves: {len(rad)} radii for {len(skeleton)} skeleton nodes")
        sect = (_tip_sections(skeleton, ksegs, bs) if len(skeleton)
                else np.zeros((0, ksegs + 1), np.int64))
        sects.append(sect)
        tip_tree.append(np.full(len(sect), t, dtype=np.int64))
        rad_all.append(rad)
    if ntree == 0:
        return []
    nodes_all, _, node_off = join_forest(skeletons)
    sect_all = np.concatenate(sects) + np.repeat(node_off[:-1], [len(x) for x in sects])[:, None]
    return leaves_at_tips(nodes_all, np.concatenate(rad_all), sect_all, np.concatenate(tip_tree), node_off[:-1],
                          method, seeds)


def _leaf_sizes(method: Union[LeafCards, NeedleClusters]):
    """(needles?, leaves or clusters per tip, length m, width m, shape name, tip segments) of ``method``;
    the width defaults to the length times the shape's aspect ratio."""
    needles = isinstance(method, NeedleClusters)
    per_tip = int(method.clusters_per_tip if needles else method.leaves_per_tip)
    length_m = float(method.cluster_length_m if needles else method.leaf_length_m)
    width_m = method.cluster_width_m if needles else method.leaf_width_m
    shape = leaf_shape_name(method.shape)
    if width_m is None:
        width_m = length_m * leaf_aspect(shape)
    return needles, per_tip, length_m, width_m, shape, int(method.tip_segments)


def leaves_at_tips(nodes: np.ndarray, radii: np.ndarray, sect_all: np.ndarray, tip_tree: np.ndarray,
                   node_start: np.ndarray, method: Union[LeafCards, NeedleClusters], seeds) -> list:
    """The leaves of :func:`grow_leaves_batch` from the trees' tip sections, one vectorised pass for all tips.

    ``nodes`` / ``radii`` the nodes of all trees (a forest), ``sect_all`` (t, K + 1) the tip sections
    (global node indices) of all trees in tree order, ``tip_tree`` (t,) the tree (0 .. n_trees - 1) of
    each, ``node_start`` (n_trees,) the index of each tree's first node, ``seeds`` one per tree.
    """
    ntree = len(seeds)
    needles, per_tip, length_m, width_m, shape, ksegs = _leaf_sizes(method)
    base_az, node_rank = phyllotaxis_azimuths(method.pattern, per_tip)
    pts = nodes[sect_all]                                        # (t, K+1, 3)
    seglen = norm3(pts[:, 1:] - pts[:, :-1])                     # (t, K)
    total = seglen.sum(axis=1)
    live = np.flatnonzero(total > 1e-9)
    tip_tree = tip_tree[live]
    nt_of = np.bincount(tip_tree, minlength=ntree)
    nt = len(live)
    n_nodes = int(node_rank.max()) + 1 if per_tip else 0
    if nt == 0 or per_tip == 0:
        return [_empty(shape, needles) for _ in range(ntree)]
    # random draws, per tree from its own generator, always in the same order: the start azimuths, then
    # normal(0, sd) azimuth, angle and roll jitters and a standard normal size jitter per leaf, drawn as
    # one block of standard normals (normal(0, sd) is 0 + sd * z of the same stream)
    starts, jitter = [], []
    for t in np.flatnonzero(nt_of).tolist():
        rng = np.random.default_rng(seeds[t])
        n_t = int(nt_of[t])
        starts.append(np.zeros(n_t) if method.pattern == "distichy" else rng.uniform(0.0, 360.0, n_t))
        jitter.append(rng.standard_normal((4, n_t, per_tip)))
    start, z = np.concatenate(starts), np.concatenate(jitter, axis=1)
    az = start[:, None] + base_az[None, :] + (0.0 + method.azimuth_jitter_deg * z[0])
    ins = method.insertion_angle_deg + (0.0 + method.angle_jitter_deg * z[1])
    ro = np.deg2rad(0.0 + method.roll_jitter_deg * z[2])
    scale = np.clip(1.0 + method.size_jitter * z[3], 0.5, 1.5)
    phi, ia = np.deg2rad(az), np.deg2rad(ins)
    # each tree's cards: those of the first direction for all its leaves, then of the second (crossed)
    ncross = 2 if method.crossed else 1
    t_off = np.r_[0, np.cumsum(nt_of)]
    first_tip = t_off[:-1][tip_tree]
    dir_step = per_tip * nt_of[tip_tree]
    card0 = ncross * per_tip * first_tip + per_tip * (np.arange(nt) - first_tip)
    base, axis, twig, corners = _leaf_kernel(
        nodes, radii, sect_all, live, seglen, total, (node_rank + 0.5) / n_nodes, np.cos(phi), np.sin(phi),
        np.cos(ia), np.sin(ia), np.cos(ro), np.sin(ro), scale, float(method.face_up), length_m, 0.5 * width_m,
        bool(method.crossed), card0, dir_step)
    L = nt * per_tip
    base, axis, twig, az = base.reshape(L, 3), axis.reshape(L, 3), twig.reshape(L, 3), az.reshape(L)
    verts_all = corners.reshape(-1, 3)
    # faces and texture coordinates number the cards of each tree from 0: one template for all
    most = ncross * per_tip * int(nt_of.max())
    faces_t = (4 * np.arange(most)[:, None, None] + np.array([[0, 1, 2], [0, 2, 3]])).reshape(-1, 3)
    uvs_t = np.tile(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]), (most, 1))
    tips_all = np.repeat(sect_all[live, -1] - node_start[tip_tree], per_tip)
    rank_all = np.tile(node_rank, nt)
    material = f"sylva_{'needles' if needles else 'leaf'}_{shape}"
    out = []
    t_l = t_off.tolist()
    for t in range(ntree):
        a, b = t_l[t], t_l[t + 1]
        if a == b:
            out.append(_empty(shape, needles))
            continue
        la, lb = a * per_tip, b * per_tip
        n = ncross * (lb - la)
        out.append(LeafMesh(verts_all[4 * ncross * la:4 * ncross * lb], faces_t[:2 * n].copy(), uvs_t[:4 * n].copy(),
                            shape, material, tips_all[la:lb], base[la:lb], axis[la:lb],
                            twig[la:lb], az[la:lb], rank_all[la:lb], {"pattern": method.pattern}))
    return out


def _empty(shape: str, needles: bool) -> LeafMesh:
    z3 = np.zeros((0, 3))
    return LeafMesh(z3, np.zeros((0, 3), dtype=np.int64), np.zeros((0, 2)), shape,
                    f"sylva_{'needles' if needles else 'leaf'}_{shape}", np.zeros(0, dtype=np.int64),
                    z3, z3, z3, np.zeros(0), np.zeros(0, dtype=np.int64))


def leaf_cards(skeleton: Skeleton, seed: int = 0, **params) -> LeafMesh:
    """``grow_leaves(skeleton, LeafCards(**params), seed)``."""
    return grow_leaves(skeleton, LeafCards(**params), seed)


def needle_clusters(skeleton: Skeleton, seed: int = 0, **params) -> LeafMesh:
    """``grow_leaves(skeleton, NeedleClusters(**params), seed)`` — for conifers."""
    return grow_leaves(skeleton, NeedleClusters(**params), seed)
