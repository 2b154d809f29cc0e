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

Everything is vectorised over all tips and leaves of a tree, or of many trees
at once (:func:`grow_leaves_batch`, same result per tree).  Cards are
single-sided quads: render them with a double-sided, alpha-masked material.
Texture coordinates follow the OBJ/OpenGL convention (v = 0 at the petiole,
the bottom row of the image; glTF writers flip v).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Union

import numpy as np

from .errors import InputError
from .geometry import _cross, branches
from .reconstruct.model import Skeleton
from .textures import leaf_aspect, leaf_texture, _shape_name

__all__ = ["PATTERNS", "GOLDEN_ANGLE_DEG", "phyllotaxis_azimuths", "LeafCards", "NeedleClusters",
           "LeafMesh", "grow_leaves", "grow_leaves_batch", "leaf_cards", "needle_clusters", "leaf_texture"]

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


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def _horizontal_normal(d: np.ndarray) -> np.ndarray:
    """Unit vectors perpendicular to ``d``: horizontal (z x d) unless ``d`` is vertical."""
    r = np.cross(np.array([0.0, 0.0, 1.0]), d)
    steep = np.linalg.norm(r, axis=1) < 1e-6
    r[steep] = np.cross(np.array([0.0, 1.0, 0.0]), d[steep])
    return _unit(r)


def _transport(v: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotate ``v`` by the minimal rotation taking unit ``a`` to unit ``b`` (row-wise)."""
    c = (a * b).sum(axis=1, keepdims=True)
    k = np.cross(a, b)
    ok = c[:, 0] > -0.999999
    out = v.copy()
    kv = np.cross(k[ok], v[ok])
    out[ok] = v[ok] * c[ok] + kv + k[ok] * ((k[ok] * v[ok]).sum(axis=1, keepdims=True) / (1.0 + c[ok]))
    return out


def _tip_sections(skeleton: Skeleton, tip_segments: int, branch_set=None):
    """Node indices (t, K + 1) of the last K segments of every branch (padded at the start)."""
    bset = branch_set if branch_set is not None else branches(skeleton)
    off = bset.offsets
    real = np.flatnonzero(np.diff(off) >= 2)
    if len(real) == 0:
        return np.zeros((0, tip_segments + 1), dtype=np.int64)
    ends, starts = off[real + 1], off[real]
    k = np.arange(tip_segments + 1)[None, :]
    pos = ends[:, None] - 1 - (tip_segments - k)
    pos = np.maximum(pos, starts[:, None])
    return bset.nodes[pos]


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
    needles = isinstance(method, NeedleClusters)
    per_tip = int(method.clusters_per_tip if needles else method.leaves_per_tip)
    length_m = float(method.cluster_length_m if needles else method.leaf_length_m)
    width_m = method.cluster_width_m if needles else method.leaf_width_m
    shape = _shape_name(method.shape)
    if width_m is None:
        width_m = length_m * leaf_aspect(shape)
    ksegs = int(method.tip_segments)
    if per_tip < 0 or ksegs < 1 or not (length_m > 0) or not (width_m > 0):
        raise InputError("leaves: need leaves_per_tip >= 0, tip_segments >= 1 and positive leaf sizes "
                         f"(got {per_tip}, {ksegs}, {length_m} m, {width_m} m)")
    base_az, node_rank = phyllotaxis_azimuths(method.pattern, per_tip)
    # tip sections of all trees; node indices made global over the concatenated skeletons
    sects, nodes_all, rad_all = [], [], []
    n_off = 0
    for skeleton, r, bs in zip(skeletons, radii, branch_sets):
        rad = skeleton.radius if r is None else np.asarray(r, dtype=np.float64).reshape(-1)
        if len(rad) != len(skeleton):
            raise InputError(f"leaves: {len(rad)} radii for {len(skeleton)} skeleton nodes")
        sect = (_tip_sections(skeleton, ksegs, bs) if len(skeleton)
                else np.zeros((0, ksegs + 1), np.int64))
        sects.append(sect + n_off)
        nodes_all.append(skeleton.nodes)
        rad_all.append(rad)
        n_off += len(skeleton)
    nodes_all = np.concatenate(nodes_all) if ntree else np.zeros((0, 3))
    rad_all = np.concatenate(rad_all) if ntree else np.zeros(0)
    sect_all = np.concatenate(sects) if ntree else np.zeros((0, ksegs + 1), np.int64)
    pts = nodes_all[sect_all]                                    # (t, K+1, 3)
    seg = pts[:, 1:] - pts[:, :-1]
    seglen = np.linalg.norm(seg, axis=2)                         # (t, K)
    total = seglen.sum(axis=1)
    live = total > 1e-9
    tip_tree = np.repeat(np.arange(ntree), [len(x) for x in sects])[live]
    nt_of = np.bincount(tip_tree, minlength=ntree)
    sect_all, pts, seg, seglen, total = sect_all[live], pts[live], seg[live], seglen[live], total[live]
    nt = len(sect_all)
    n_nodes = int(node_rank.max()) + 1 if per_tip else 0
    if nt == 0 or per_tip == 0:
        return [_empty(shape, needles) for _ in range(ntree)]
    # random draws, per tree from its own generator, always in the same order
    draws = [[], [], [], [], []]
    for t in np.flatnonzero(nt_of):
        rng = np.random.default_rng(seeds[t])
        n_t = int(nt_of[t])
        draws[0].append(np.zeros(n_t) if method.pattern == "distichy" else rng.uniform(0.0, 360.0, n_t))
        draws[1].append(rng.normal(0.0, method.azimuth_jitter_deg, (n_t, per_tip)))
        draws[2].append(rng.normal(0.0, method.angle_jitter_deg, (n_t, per_tip)))
        draws[3].append(rng.normal(0.0, method.roll_jitter_deg, (n_t, per_tip)))
        draws[4].append(rng.standard_normal((n_t, per_tip)))
    start, az_jit, ins_jit, roll, size_jit = (np.concatenate(d) for d in draws)
    # unit directions per segment; zero-length (padding) segments take the next real one
    d = seg / np.where(seglen > 0, seglen, 1.0)[..., None]
    for q in range(ksegs - 2, -1, -1):
        zero = seglen[:, q] <= 0
        d[zero, q] = d[zero, q + 1]
    # reference normal per segment: horizontal at the first, carried by minimal rotations
    ref = np.empty_like(d)
    ref[:, 0] = _horizontal_normal(d[:, 0])
    for q in range(1, ksegs):
        ref[:, q] = _unit(_transport(ref[:, q - 1], d[:, q - 1], d[:, q]))
    # leaf positions along the tip section
    cum = np.concatenate([np.zeros((nt, 1)), np.cumsum(seglen, axis=1)], axis=1)   # (t, K+1)
    frac = (node_rank + 0.5) / n_nodes                                               # (L,)
    s = total[:, None] * frac[None, :]                                               # (t, L)
    q = np.clip((cum[:, None, 1:-1] <= s[..., None]).sum(axis=2), 0, ksegs - 1)       # (t, L)
    ti = np.arange(nt)[:, None]
    local = (s - cum[ti, q]) / np.where(seglen[ti, q] > 0, seglen[ti, q], 1.0)
    pos = pts[ti, q] + local[..., None] * seg[ti, q]
    twig = d[ti, q]                                                                  # (t, L, 3)
    r_ = ref[ti, q]
    r_ = _unit(r_ - (r_ * twig).sum(axis=2, keepdims=True) * twig)
    s_ = _cross(twig, r_)
    # radii along the twig (linear between nodes)
    rn = rad_all[sect_all]
    rad_at = rn[ti, q] + local * (rn[ti, q + 1] - rn[ti, q])
    az = start[:, None] + base_az[None, :] + az_jit
    ins = method.insertion_angle_deg + ins_jit
    scale = np.clip(1.0 + method.size_jitter * size_jit, 0.5, 1.5)
    phi = np.deg2rad(az)[..., None]
    out_dir = np.cos(phi) * r_ + np.sin(phi) * s_            # radial direction of the leaf
    wdir = -np.sin(phi) * r_ + np.cos(phi) * s_              # across the blade
    ia = np.deg2rad(ins)[..., None]
    axis = np.cos(ia) * twig + np.sin(ia) * out_dir
    ro = np.deg2rad(roll)[..., None]
    wdir = np.cos(ro) * wdir + np.sin(ro) * _cross(axis, wdir)
    if method.face_up > 0:
        horiz = _cross(axis, np.array([0.0, 0.0, 1.0]))
        hn = np.linalg.norm(horiz, axis=2, keepdims=True)
        horiz = np.where(hn > 1e-6, horiz / np.where(hn > 0, hn, 1.0), wdir)
        horiz *= np.sign((horiz * wdir).sum(axis=2, keepdims=True) + 1e-12)
        wdir = (1.0 - method.face_up) * wdir + method.face_up * horiz
        wdir = _unit(wdir - (wdir * axis).sum(axis=2, keepdims=True) * axis)
    base = pos + rad_at[..., None] * out_dir
    length = (length_m * scale)[..., None]
    half_w = (0.5 * width_m * scale)[..., None]
    # flatten leaves
    L = nt * per_tip
    base, axis, wdir, twig = (x.reshape(L, 3) for x in (base, axis, wdir, twig))
    length, half_w = length.reshape(L, 1), half_w.reshape(L, 1)
    dirs = [wdir, _cross(axis, wdir)] if method.crossed else [wdir]
    tip_pt = base + length * axis
    corners = [np.stack([base - half_w * w, base + half_w * w,
                         tip_pt + half_w * w, tip_pt - half_w * w], axis=1) for w in dirs]     # (L, 4, 3)
    az = az.reshape(L)
    tips_local = sect_all[:, -1] - np.repeat(np.r_[0, np.cumsum([len(sk) for sk in skeletons])][:-1], nt_of)
    quad_uv = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    material = f"sylva_{'needles' if needles else 'leaf'}_{shape}"
    out = []
    t_off = np.r_[0, np.cumsum(nt_of)].tolist()
    for t in range(ntree):
        a, b = t_off[t], t_off[t + 1]
        if a == b:
            out.append(_empty(shape, needles))
            continue
        la, lb = a * per_tip, b * per_tip
        Lt = lb - la
        verts, uvs, faces = [], [], []
        nv = 0
        for c in corners:
            verts.append(c[la:lb].reshape(-1, 3))
            uvs.append(np.tile(quad_uv, (Lt, 1)))
            v0 = nv + 4 * np.arange(Lt)[:, None]
            faces.append(np.concatenate([v0 + [0, 1, 2], v0 + [0, 2, 3]], axis=1).reshape(-1, 3))
            nv += 4 * Lt
        out.append(LeafMesh(np.concatenate(verts), np.concatenate(faces).astype(np.int64), np.concatenate(uvs),
                            shape, material, np.repeat(tips_local[a:b], per_tip), base[la:lb], axis[la:lb],
                            twig[la:lb], az[la:lb], np.tile(node_rank, b - a), {"pattern": method.pattern}))
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
