"""Leaves at branch tips (Hu et al. 2017 §5.6): phyllotaxis, leaf cards, needle clusters, textures."""
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from sylva.core import geometry as G
from sylva.core import leaves as LV
from sylva.core import textures as TX
from sylva.core.errors import InputError
from sylva.core.skeleton import Skeleton

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("geometry_bench", ROOT / "benchmarks" / "geometry.py")
_bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_bench)
random_skeleton = _bench.random_skeleton

NO_JITTER = dict(azimuth_jitter_deg=0.0, angle_jitter_deg=0.0, roll_jitter_deg=0.0, size_jitter=0.0)


def stem(n=6, height=5.0, direction=(0, 0, 1)):
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    nodes = np.linspace(0, height, n)[:, None] * d
    return Skeleton(nodes, np.r_[-1, np.arange(n - 1)], radius=np.full(n, 0.02))


def azimuths_around_twig(lm):
    """Angle of each leaf axis around its twig, measured in a fixed plane frame."""
    t = lm.twig[0]
    ref = np.cross([0.0, 0.0, 1.0], t) if abs(t[2]) < 0.99 else np.array([1.0, 0, 0])
    ref /= np.linalg.norm(ref)
    other = np.cross(t, ref)
    p = lm.axis - np.outer(lm.axis @ t, t)
    return np.degrees(np.arctan2(p @ other, p @ ref))


@pytest.mark.parametrize("pattern,step", [("distichy", 180.0), ("dispersion", 137.5077640500378)])
@pytest.mark.parametrize("direction", [(0, 0, 1), (1, 0.2, 0.1)])
def test_successive_leaves_turn_by_the_pattern_angle(pattern, step, direction):
    lm = LV.grow_leaves(stem(direction=direction), LV.LeafCards(pattern=pattern, leaves_per_tip=9, **NO_JITTER))
    assert lm.n_leaves == 9
    turn = np.diff(azimuths_around_twig(lm)) % 360.0
    assert np.allclose(turn, step, atol=1e-9)
    assert np.allclose(np.diff(lm.azimuth_deg), step)


def test_decussation_opposite_pairs_turned_90_degrees():
    lm = LV.grow_leaves(stem(), LV.LeafCards(pattern="decussation", leaves_per_tip=8, **NO_JITTER))
    az = azimuths_around_twig(lm)
    z = lm.base[:, 2]
    assert np.allclose(z[0::2], z[1::2])                              # two leaves per node
    assert np.all(np.diff(z[0::2]) > 0)
    assert np.allclose((az[1::2] - az[0::2]) % 360, 180.0, atol=1e-9)  # opposite
    assert np.allclose(np.diff(az[0::2]) % 360, 90.0, atol=1e-9)       # decussate


def test_leaves_sit_on_the_last_three_segments_at_the_twig_surface():
    sk = stem(n=8, height=7.0)                                        # nodes 1 m apart
    lm = LV.grow_leaves(sk, LV.LeafCards(leaves_per_tip=10, insertion_angle_deg=50, **NO_JITTER))
    radial = np.hypot(lm.base[:, 0], lm.base[:, 1])
    assert np.allclose(radial, 0.02)                                  # on the twig surface
    assert lm.base[:, 2].min() > 4.0 and lm.base[:, 2].max() < 7.0    # segments (4,5), (5,6), (6,7)
    tilt = np.degrees(np.arccos(lm.axis @ np.array([0, 0, 1.0])))
    assert np.allclose(tilt, 50.0)
    # cards: length 0.10 m along the axis, width length * aspect
    quads = lm.vertices.reshape(-1, 4, 3)
    assert np.allclose(np.linalg.norm(quads[:, 3] - quads[:, 0], axis=1), 0.10)
    assert np.allclose(np.linalg.norm(quads[:, 1] - quads[:, 0], axis=1), 0.10 * TX.leaf_aspect("ovate"))
    assert lm.faces.shape == (20, 3) and lm.faces.max() == 39
    assert lm.uvs.min() == 0.0 and lm.uvs.max() == 1.0
    assert np.allclose(lm.uvs[:4], [[0, 0], [1, 0], [1, 1], [0, 1]])


def test_counts_per_tip_on_a_tree_and_determinism():
    sk = random_skeleton(300, seed=3)
    sk = G.with_radii(sk, G.pipe_model_radii(sk))
    n_tips = len(sk.tips())
    lm = LV.grow_leaves(sk, LV.LeafCards(leaves_per_tip=7), seed=11)
    assert lm.n_leaves == 7 * n_tips
    assert np.array_equal(np.sort(np.unique(lm.tip)), np.sort(sk.tips()))
    assert np.all(np.bincount(lm.tip, minlength=len(sk))[sk.tips()] == 7)
    assert len(lm.vertices) == 4 * lm.n_leaves and len(lm.faces) == 2 * lm.n_leaves
    again = LV.grow_leaves(sk, LV.LeafCards(leaves_per_tip=7), seed=11)
    assert np.array_equal(lm.vertices, again.vertices) and np.array_equal(lm.uvs, again.uvs)
    other = LV.grow_leaves(sk, LV.LeafCards(leaves_per_tip=7), seed=12)
    assert not np.allclose(lm.vertices, other.vertices)
    # leaves stay near their tips: within three segments plus a leaf length
    dist = np.linalg.norm(lm.base - sk.nodes[lm.tip], axis=1)
    assert dist.max() < 3 * 0.6 + 0.2


def test_needle_clusters_are_crossed_quads():
    sk = random_skeleton(120, seed=1)
    nm = LV.grow_leaves(sk, LV.NeedleClusters(clusters_per_tip=5), seed=2)
    n = nm.n_leaves
    assert n == 5 * len(sk.tips())
    assert len(nm.vertices) == 8 * n and len(nm.faces) == 4 * n
    assert nm.texture == "needle_spray" and "needles" in nm.material
    first = nm.vertices[: 4 * n].reshape(n, 4, 3)
    second = nm.vertices[4 * n:].reshape(n, 4, 3)
    w1 = first[:, 1] - first[:, 0]
    w2 = second[:, 1] - second[:, 0]
    assert np.allclose(np.einsum("ij,ij->i", w1, w2), 0, atol=1e-12)   # crossed at 90°
    assert np.allclose(first[:, 0] + first[:, 1], second[:, 0] + second[:, 1])  # same axis
    assert np.allclose(np.einsum("ij,ij->i", w1, nm.axis), 0, atol=1e-12)


def test_leaf_mesh_to_trimesh_and_bad_input():
    lm = LV.leaf_cards(stem(), seed=0, leaves_per_tip=4, shape="maple")
    assert lm.texture == "palmate"
    mesh = lm.to_trimesh(texture_size=32)
    assert len(mesh.faces) == 8
    with pytest.raises(InputError, match="phyllotaxis"):
        LV.grow_leaves(stem(), LV.LeafCards(pattern="whorled"))
    with pytest.raises(InputError, match="leaf shape"):
        LV.grow_leaves(stem(), LV.LeafCards(shape="banana"))
    empty = LV.grow_leaves(Skeleton(np.zeros((1, 3)), np.array([-1])))
    assert empty.n_leaves == 0 and empty.vertices.shape == (0, 3)


# --------------------------------------------------------------------------- textures

@pytest.mark.parametrize("shape", TX.LEAF_SHAPES)
def test_leaf_textures_have_transparent_background_and_opaque_leaf(shape):
    img = TX.leaf_texture(shape, 128)
    assert img.shape == (128, 128, 4) and img.dtype == np.uint8
    alpha = img[..., 3]
    assert alpha[0, 0] == alpha[0, -1] == alpha[-1, 0] == alpha[-1, -1] == 0
    assert alpha[-1, 64] == 255 or alpha[-1, 63] == 255               # petiole / twig at bottom centre
    assert alpha[70, 64] == 255 or alpha[70, 63] == 255               # blade around the middle
    opaque = (alpha == 255).mean()
    assert 0.05 < opaque < 0.8
    assert ((alpha > 0) & (alpha < 255)).any()                        # antialiased edge
    assert np.array_equal(img, TX.leaf_texture(shape, 128))           # deterministic
    green = img[alpha == 255][:, :3].astype(int)
    assert (green[:, 1] >= green[:, 2]).mean() > 0.9


def test_shapes_differ_and_species_alias():
    imgs = {s: TX.leaf_texture(s, 64)[..., 3] > 127 for s in TX.LEAF_SHAPES}
    names = list(imgs)
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            assert (imgs[names[i]] != imgs[names[j]]).mean() > 0.03, (names[i], names[j])
    assert np.array_equal(TX.leaf_texture("apple", 64), TX.leaf_texture("ovate", 64))


def test_png_writer_round_trip(tmp_path, monkeypatch):
    Image = pytest.importorskip("PIL.Image")
    img = TX.leaf_texture("lobed", 48)
    path = TX.write_png(tmp_path / "lobed.png", img)
    assert TX.read_png_size(path) == (48, 48)
    assert np.array_equal(np.asarray(Image.open(path).convert("RGBA")), img)
    # the fallback zlib writer (no Pillow) gives the same pixels
    import builtins

    real_import = builtins.__import__

    def no_pil(name, *a, **k):
        if name == "PIL" or name.startswith("PIL."):
            raise ImportError(name)
        return real_import(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_pil)
    path2 = TX.write_png(tmp_path / "fallback.png", img)
    monkeypatch.undo()
    assert np.array_equal(np.asarray(Image.open(path2).convert("RGBA")), img)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fallback.png", "lobed.png"]  # no temp files left


def test_shipped_textures_match_the_drawing():
    folder = ROOT / "resources" / "leaves"
    if not folder.is_dir():
        pytest.skip("resources/leaves not generated (python scripts/make_leaf_textures.py)")
    Image = pytest.importorskip("PIL.Image")
    for shape in TX.LEAF_SHAPES:
        png = folder / f"{shape}.png"
        assert png.exists(), png
        img = np.asarray(Image.open(png).convert("RGBA"))
        assert np.array_equal(img, TX.leaf_texture(shape, img.shape[0]))
