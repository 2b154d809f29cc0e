"""Billboard trees (Zhou et al. 2013 §VI): shape fitting, textures, GLB/3D Tiles output, sylva:billboards."""
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sylva.core.errors import EmptyInputError, InputError
from sylva.core.export import ExportFrame, write_glb, write_tileset
from sylva.core.export.georef import Georef
from sylva.core.export.gltf import glb_bytes, node_world_positions, read_glb
from sylva.core.export.model import TreeModel
from sylva.core.export.tiles3d import coarse_error
from sylva.core.reconstruct.billboard import (Billboard, Orthophoto, PinholeCamera, bhattacharyya, billboard_tree,
                                              complete_blocks, opaque_points, ransac_line, read_orthophoto,
                                              sample_camera, sample_orthophoto)

ROOT = Path(__file__).resolve().parents[1]
VIEWERS = ROOT / "tools" / "viewers"
GREEN, BROWN, SKY = (50, 120, 40), (110, 80, 50), (120, 170, 235)


def make_tree(seed=0, lean=(0.0, 0.0), trunk_r=0.15, trunk_h=5.0, crown_r=3.0, crown_top=12.0,
              n_trunk=3000, n_crown=8000, second_trunk_dx=None, sky_fraction=0.0):
    """A stem (cylinder surface, leaning by ``lean`` m per m) under an ellipsoidal crown shell; RGB per point."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(0, trunk_h + 1.0, n_trunk)
    a = rng.uniform(0, 2 * np.pi, n_trunk)
    trunk = np.column_stack([lean[0] * z + trunk_r * np.cos(a), lean[1] * z + trunk_r * np.sin(a), z])
    if second_trunk_dx is not None:
        trunk = np.vstack([trunk, trunk + [second_trunk_dx, 0.0, 0.0]])
    u = rng.normal(size=(n_crown, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    u *= rng.uniform(0.7, 1.0, n_crown)[:, None]
    cz, hz = (trunk_h + crown_top) / 2, (crown_top - trunk_h) / 2
    crown = np.column_stack([lean[0] * cz + crown_r * u[:, 0], lean[1] * cz + crown_r * u[:, 1], cz + hz * u[:, 2]])
    rgb = np.vstack([np.tile(BROWN, (len(trunk), 1)), np.tile(GREEN, (len(crown), 1))]).astype(float)
    if sky_fraction:
        sky = len(trunk) + np.flatnonzero(rng.uniform(size=len(crown)) < sky_fraction)
        rgb[sky] = SKY  # misaligned image: sky seen through the crown (§VI-B, Fig. 6a)
    rgb = np.clip(rgb + rng.normal(0, 6, rgb.shape), 0, 255).astype(np.uint8)
    return np.vstack([trunk, crown]), rgb, dict(lean=np.array(lean), cz=cz)


def texels_at(bb, quad, pts):
    """Atlas texels (RGBA) under points projected perpendicularly onto quad ``quad`` (None outside it)."""
    v = bb.vertices[4 * quad:4 * quad + 4]
    uv = bb.uvs[4 * quad:4 * quad + 4]
    basis = np.column_stack([v[1] - v[0], v[3] - v[0]])        # a parallelogram when the trunk leans
    fu, fv = np.linalg.pinv(basis) @ (pts - v[0]).T
    inside = (fu >= 0) & (fu < 1) & (fv >= 0) & (fv < 1)
    H, W = bb.texture.shape[:2]
    u = uv[0, 0] + fu * (uv[1, 0] - uv[0, 0])
    t = uv[0, 1] + fv * (uv[3, 1] - uv[0, 1])
    col = np.clip((u * W).astype(int), 0, W - 1)
    row = np.clip(((1 - t) * H).astype(int), 0, H - 1)
    return bb.texture[row, col], inside


# --------------------------------------------------------------------------- shape fitting (§VI-A)

def test_trunk_axis_and_crown_box_of_a_leaning_tree():
    xyz, rgb, truth = make_tree(lean=(0.06, -0.03))
    bb = billboard_tree(xyz, rgb=rgb, ground_z=0.0, tree_id=4)
    assert bb.has_trunk and bb.quad_kind == ("crown",) * 3 + ("trunk",) * 3
    assert bb.vertices.shape == (24, 3) and bb.faces.shape == (12, 3) and bb.uvs.shape == (24, 2)
    # origin at the stem base: the trunk axis starts at (0, 0, 0); its direction is the lean
    bottom, top = bb.trunk_axis
    np.testing.assert_allclose(bottom, 0.0, atol=1e-9)
    direction = (top - bottom)[:2] / (top - bottom)[2]
    np.testing.assert_allclose(direction, truth["lean"], atol=0.015)
    assert bb.trunk_height_m == pytest.approx(5.0, abs=0.3)       # crown base at 5 m
    assert bb.trunk_width_m == pytest.approx(0.30, abs=0.08)      # stem diameter
    # crown axis at the crown centre (relative to the stem base), boxes 6 m wide from 5 m to 12 m
    np.testing.assert_allclose(bb.crown_axis, truth["lean"] * truth["cz"], atol=0.1)
    box = bb.crown_boxes
    np.testing.assert_allclose(box[:, 1] - box[:, 0], 6.0, atol=0.25)
    np.testing.assert_allclose(box[:, 0], -3.0, atol=0.2)
    np.testing.assert_allclose(box[:, 2], 5.0, atol=0.3)
    np.testing.assert_allclose(box[:, 3], 12.0, atol=0.1)
    # the quads: crown quads vertical, 60 degrees apart, around the crown axis; in metres
    crown = bb.vertices[:12].reshape(3, 4, 3)
    assert np.allclose(crown[:, 0, :2], crown[:, 3, :2]) and np.allclose(crown[:, 0, 2], crown[:, 1, 2])
    d = crown[:, 1, :2] - crown[:, 0, :2]
    ang = np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 180
    np.testing.assert_allclose(np.diff(np.sort(ang)), 60.0, atol=1e-6)
    assert bb.vertices[:, 2].max() == pytest.approx(12.0, abs=0.1)


def test_trees_without_a_single_trunk_get_crown_quads_only():
    # two stems side by side (Fig. 5)
    xyz, rgb, _ = make_tree(seed=1, second_trunk_dx=1.2)
    bb = billboard_tree(xyz, rgb=rgb, ground_z=0.0)
    assert not bb.has_trunk and bb.quad_kind == ("crown",) * 3 and len(bb.faces) == 6
    assert bb.trunk_axis is None and bb.trunk_height_m == 0.0
    np.testing.assert_allclose(bb.crown_boxes[:, 2], 0.0, atol=0.1)  # the whole tree is crown
    # an airborne-like tree: no stem points below the crown
    xyz, rgb, _ = make_tree(seed=2)
    keep = xyz[:, 2] > 5.3
    bb = billboard_tree(xyz[keep], rgb=rgb[keep], ground_z=0.0)
    assert not bb.has_trunk and len(bb.faces) == 6
    assert bb.vertices[:, 2].min() == pytest.approx(5.3, abs=0.1)
    # given a DBH, the unseen stem is drawn from the ground into the crown, with bark
    stem = billboard_tree(xyz[keep], rgb=rgb[keep], ground_z=0.0, stem_diameter_m=0.3)
    assert stem.quad_kind == ("crown",) * 3 + ("stem",) * 3 and not stem.has_trunk
    quads = stem.vertices.reshape(-1, 4, 3)
    assert quads[3:, :, 2].min() == pytest.approx(0.0) and 5.3 < quads[3:, :, 2].max() < 7.0
    widths = np.linalg.norm(quads[3:, 1] - quads[3:, 0], axis=1)
    np.testing.assert_allclose(widths, 0.3)
    # several stems keep Zhou's rule: crown quads only, even with a DBH
    xyz2, rgb2, _ = make_tree(seed=1, second_trunk_dx=1.5)
    assert billboard_tree(xyz2, rgb=rgb2, ground_z=0.0, stem_diameter_m=0.3).quad_kind == ("crown",) * 3


def test_ransac_line_is_seeded_and_ignores_outliers():
    rng = np.random.default_rng(3)
    y = np.linspace(0, 5, 60)
    x = 0.1 * y + 2.0 + rng.normal(0, 0.005, 60)
    x[::7] += rng.uniform(0.5, 2.0, len(x[::7]))
    a, b, frac = ransac_line(y, x, 100, 0.03, np.random.default_rng(0))
    assert a == pytest.approx(0.1, abs=0.005) and b == pytest.approx(2.0, abs=0.01)
    assert 0.8 < frac < 0.9
    assert ransac_line(y, x, 100, 0.03, np.random.default_rng(0)) == (a, b, frac)
    assert ransac_line(y[:1], x[:1], 10, 0.03, np.random.default_rng(0)) is None


# --------------------------------------------------------------------------- textures (§VI-B)

def test_textures_are_opaque_where_the_points_are_and_take_their_colours():
    xyz, rgb, _ = make_tree(lean=(0.04, 0.0))
    bb = billboard_tree(xyz, rgb=rgb, ground_z=0.0)
    assert bb.texture_source == "points" and bb.texture.dtype == np.uint8 and bb.texture.shape[2] == 4
    assert set(np.unique(bb.texture[..., 3])) == {0, 255}
    crown_pts = xyz[len(xyz) - 8000:]
    for q in range(3):
        texel, inside = texels_at(bb, q, crown_pts)
        assert inside.mean() > 0.99
        assert (texel[inside, 3] == 255).mean() > 0.97
        c = texel[inside & (texel[:, 3] == 255), :3].astype(int).mean(axis=0)
        np.testing.assert_allclose(c, GREEN, atol=12)
    trunk_pts = xyz[(xyz[:, 2] > 0.5) & (xyz[:, 2] < 4.5)][:2000]
    for q in range(3, 6):
        texel, inside = texels_at(bb, q, trunk_pts)
        assert inside.mean() > 0.95
        opaque = texel[inside, 3] == 255
        assert opaque.mean() > 0.9
        np.testing.assert_allclose(texel[inside][opaque, :3].astype(int).mean(axis=0), BROWN, atol=15)
    # outside the silhouette the atlas is transparent: a quad is not a filled rectangle
    assert 0.15 < (bb.texture[..., 3] == 0).mean() < 0.8


def test_gmm_removes_wrong_colours_and_blocks_fill_them():
    xyz, rgb, _ = make_tree(seed=5, sky_fraction=0.25)
    blue = lambda t: ((t[..., 2].astype(int) > t[..., 1] + 30) & (t[..., 3] == 255)).sum()  # noqa: E731
    raw = billboard_tree(xyz, Billboard(gmm_components=0), rgb=rgb, ground_z=0.0)
    clean = billboard_tree(xyz, Billboard(gmm_components=2), rgb=rgb, ground_z=0.0)
    assert blue(raw.texture) > 200
    assert blue(clean.texture) < 0.05 * blue(raw.texture)
    # the removed texels are filled (Algorithm 1), not left transparent
    assert (clean.texture[..., 3] == 255).sum() == (raw.texture[..., 3] == 255).sum()


def test_block_completion_and_bhattacharyya():
    h1 = np.array([1.0, 2.0, 3.0, 0.0])
    assert bhattacharyya(h1, h1) == pytest.approx(0.0, abs=1e-7)
    assert bhattacharyya(h1, np.array([0.0, 0.0, 0.0, 5.0])) == pytest.approx(1.0)
    assert bhattacharyya(h1, 3 * h1) == pytest.approx(0.0, abs=1e-7)  # normalised by the means (Eq. 3)
    rng = np.random.default_rng(0)
    img = np.zeros((48, 48, 3))
    img[:, :24] = (0.2, 0.5, 0.1)            # left: green
    img[:, 24:] = (0.4, 0.3, 0.2)            # right: brown
    img += rng.normal(0, 0.01, img.shape)
    mask = np.ones((48, 48), bool)
    good = mask.copy()
    good[16:32, 4:20] = False                # a hole in the green half
    img_bad = img.copy()
    img_bad[~good] = (0.5, 0.7, 0.9)
    out, s = complete_blocks(img_bad, mask, good, Billboard(block_px=8), np.random.default_rng(0))
    assert s == 8
    filled = out[16:32, 4:20]
    np.testing.assert_allclose(filled.reshape(-1, 3).mean(axis=0), (0.2, 0.5, 0.1), atol=0.03)
    np.testing.assert_array_equal(out[good], img_bad[good])
    # nothing correct anywhere: no candidate block, the caller draws a procedural texture
    out, s = complete_blocks(img_bad, mask, np.zeros_like(mask), Billboard(), np.random.default_rng(0))
    assert s == 0


def test_fast_paths_equal_the_straightforward_computations():
    """The speed-ups (module docstring) give exactly what distance transforms, a k-d tree of all points,
    binary_fill_holes and scikit-learn's GaussianMixture give."""
    import warnings

    from scipy import ndimage
    from sklearn.mixture import GaussianMixture

    from sylva.core.reconstruct.billboard import shape as bbm
    from sylva.core.reconstruct.billboard import texture as bbt

    rng = np.random.default_rng(3)
    for r in (1, 3, 7, 12):                      # closing by exact discs
        occ = rng.uniform(size=(70, 50)) < 0.04
        occ[:r + 2] = occ[-r - 2:] = False
        occ[:, :r + 2] = occ[:, -r - 2:] = False
        occ[35, 25] = True
        dil = ndimage.distance_transform_edt(~occ) <= r
        np.testing.assert_array_equal(bbm._disc_dilate(occ, r), dil)
        np.testing.assert_array_equal(~bbm._disc_dilate(~dil, r), ndimage.distance_transform_edt(dil) > r)
        np.testing.assert_array_equal(bbm._fill_holes(dil), ndimage.binary_fill_holes(dil))
    # shape mask (stamped and row-gap dilations) against the distance-transform version
    for n_pts, close_px in ((300, 9), (20000, 3)):
        s, z = rng.uniform(0, 6, n_pts), rng.uniform(0, 9, n_pts)
        mask, s0, z0 = bbm.shape_mask(s, z, 0.05, close_px)
        col, row = np.floor((s - s0) / 0.05).astype(int), np.floor((z - z0) / 0.05).astype(int)
        occ = np.zeros(mask.shape, bool)
        occ[row, col] = True
        ref = (ndimage.distance_transform_edt(ndimage.distance_transform_edt(~occ) <= close_px) > close_px) | occ
        ref = ndimage.binary_fill_holes(ref)
        lab, n = ndimage.label(ref, structure=np.ones((3, 3), bool))
        sizes = np.bincount(lab.ravel())[1:]
        np.testing.assert_array_equal(mask, np.r_[False, sizes >= 0.05 * sizes.max()][lab])
    # closing radius: the subset bound gives the k-d tree of all points' answer
    method = Billboard()
    for xyz in (make_tree(n_trunk=4000, n_crown=20000)[0], rng.uniform(0, 20, (9000, 3))):
        full = int(np.ceil(min(max(method.close_m, bbm._spacing(xyz)), method.max_close_m) / method.pixel_m))
        assert bbm._close_px(xyz, method) == full
    # EM: the labels of scikit-learn's GaussianMixture with the same seed
    rgb = np.vstack([rng.normal((0.2, 0.47, 0.16), 0.03, (3000, 3)), rng.normal((0.47, 0.67, 0.92), 0.03, (800, 3))])
    rgb = np.clip(rgb, 0, 1)
    feats = bbt._hsv_cone(rgb)
    train = feats[np.sort(np.random.default_rng(11).choice(len(rgb), 1500, replace=False))]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gmm = GaussianMixture(2, covariance_type="diag", max_iter=50, reg_covar=1e-4, init_params="k-means++",
                              random_state=11).fit(train)
    ref = gmm.predict(feats) == int(np.argmin(np.linalg.norm(gmm.means_ - feats.mean(axis=0), axis=1)))
    keep = bbt.gmm_clean(rgb, 2, 11)
    np.testing.assert_array_equal(keep, ref)
    assert keep[:3000].all() and not keep[3000:].any()


def test_procedural_texture_without_colours_and_bad_input():
    xyz, _, _ = make_tree(seed=7)
    bb = billboard_tree(xyz, ground_z=0.0)
    assert bb.texture_source == "procedural"
    crown = bb.texture[..., 3] == 255
    assert crown.mean() > 0.2
    g = bb.texture[crown].astype(int)
    assert np.median(g[:, 1]) > np.median(g[:, 2])       # greenish/brown, never empty
    with pytest.raises(EmptyInputError, match="tree 9"):
        billboard_tree(np.zeros((0, 3)), tree_id=9)
    with pytest.raises(InputError, match="colours"):
        billboard_tree(xyz, rgb=np.zeros((3, 3), np.uint8))
    with pytest.raises(InputError, match="pixel_m"):
        Billboard(pixel_m=0)
    tiny = billboard_tree(np.array([[0.0, 0.0, 3.0], [0.1, 0.0, 3.2], [0.0, 0.1, 3.4]]), ground_z=0.0)
    assert len(tiny.faces) == 6 and np.all(np.isfinite(tiny.vertices))


def test_colours_from_an_orthophoto_and_a_pinhole_camera(tmp_path):
    import tifffile

    rgb = np.zeros((20, 30, 3), np.uint8)
    rgb[:, :15] = (200, 0, 0)
    rgb[:, 15:] = (0, 0, 200)
    # GeoTIFF: pixel 0.5 m, north-west corner (1000, 2010), EPSG:32632
    keys = (1, 1, 0, 3, 1024, 0, 1, 1, 1025, 0, 1, 1, 3072, 0, 1, 32632)
    path = tmp_path / "ortho.tif"
    tifffile.imwrite(path, rgb, photometric="rgb", extratags=[
        (33550, "d", 3, (0.5, 0.5, 0.0)), (33922, "d", 6, (0, 0, 0, 1000.0, 2010.0, 0.0)),
        (34735, "H", len(keys), keys)])
    ortho = read_orthophoto(path)
    assert ortho.rgb.shape == (20, 30, 3) and ortho.crs.to_epsg() == 32632
    c = sample_orthophoto(ortho, [1001.0, 1012.0, 990.0], [2005.0, 2005.0, 2005.0])
    np.testing.assert_allclose(c[0], (200 / 255, 0, 0))
    np.testing.assert_allclose(c[1], (0, 0, 200 / 255))
    assert np.isnan(c[2]).all()
    with pytest.raises(InputError, match="not found"):
        read_orthophoto(tmp_path / "missing.tif")
    grey = Orthophoto.from_raster(type("R", (), dict(data=np.array([[0.0, np.nan], [2.0, 4.0]]), x0=0, y0=2,
                                                     pixel=1.0, crs=None))())
    assert grey.rgb[1, 1].tolist() == [255, 255, 255] and not grey.valid[0, 1]
    # a camera at the origin looking north (+y); image 100 x 80, f = 50 px
    image = np.zeros((80, 100, 3), np.uint8)
    image[:40] = (0, 0, 255)          # upper half (sky)
    image[40:] = (0, 255, 0)          # lower half
    K = np.array([[50.0, 0, 50], [0, 50.0, 40], [0, 0, 1]])
    R = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])       # world (x east, y north, z up) -> camera (x, y down, z ahead)
    cam = PinholeCamera(K, R, np.zeros(3), image)
    c = sample_camera(cam, [[0, 10, 2], [0, 10, -2], [0, -10, 0], [100, 1, 0]])
    np.testing.assert_allclose(c[0], (0, 0, 1))
    np.testing.assert_allclose(c[1], (0, 1, 0))
    assert np.isnan(c[2:]).all()     # behind the camera; outside the image


def test_deterministic():
    xyz, rgb, _ = make_tree(seed=11, lean=(0.02, 0.05), sky_fraction=0.1)
    a = billboard_tree(xyz, rgb=rgb, ground_z=0.0, tree_id=3)
    b = billboard_tree(xyz, rgb=rgb, ground_z=0.0, tree_id=3)
    for name in ("vertices", "faces", "uvs", "texture", "crown_boxes", "trunk_axis"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert a.png() == b.png()


# --------------------------------------------------------------------------- export

@pytest.fixture(scope="module")
def billboard_models():
    models = []
    for k in range(4):
        xyz, rgb, _ = make_tree(seed=20 + k, lean=(0.03 * k, 0.0), crown_r=2.0 + k, n_trunk=1500, n_crown=5000,
                                second_trunk_dx=1.2 if k == 3 else None)
        bb = billboard_tree(xyz, rgb=rgb, ground_z=0.0, tree_id=k + 1)
        base = np.array([500000.0 + 12 * k, 5400000.0 + 5 * k, 300.0 + k]) + np.r_[bb.origin[:2], 0]
        models.append(TreeModel(k + 1, base, None, attributes={"height": 12.0, **bb.summary()}, billboard=bb))
    return models


def test_glb_of_billboards(tmp_path, billboard_models):
    frame = ExportFrame("EPSG:32632")
    path = tmp_path / "bb.glb"
    write_glb(billboard_models, path, frame, content="billboard")
    size = path.stat().st_size
    assert size <= 40_000 * len(billboard_models)   # Zhou et al. Table II: ~40 kB a tree with its texture
    doc, binary = read_glb(path)
    mats = {m["name"]: m for m in doc["materials"]}
    for m in billboard_models:
        mat = mats[f"billboard_{m.tree_id}"]
        assert mat["alphaMode"] == "MASK" and mat["doubleSided"] is True
        mesh = next(x for x in doc["meshes"] if x["name"] == m.name)
        prim, = mesh["primitives"]
        assert doc["materials"][prim["material"]] is not None and "TEXCOORD_0" in prim["attributes"]
        assert prim["extensions"]["EXT_mesh_features"]["featureIds"][0]["featureCount"] == len(billboard_models)
    assert all(im["mimeType"] == "image/png" for im in doc["images"]) and len(doc["images"]) == 4
    table = doc["extensions"]["EXT_structural_metadata"]["propertyTables"][0]
    assert table["count"] == 4 and "bb_has_trunk" in table["properties"]
    # the quads are where the billboard says, in the source CRS, within 1 cm
    origin = json.loads(path.with_name("bb.origin.json").read_text())["origin_source"]
    georef = Georef(frame, origin)
    for m in billboard_models:
        enu = node_world_positions(doc, binary, m.name)
        src = georef.enu_to_source(enu)
        np.testing.assert_allclose(np.sort(src, axis=0), np.sort(m.base + m.billboard.vertices, axis=0), atol=0.01)
    # deterministic bytes
    assert glb_bytes(billboard_models, georef, content="billboard") == glb_bytes(billboard_models, georef,
                                                                               content="billboard")
    with pytest.raises(InputError, match="content"):
        glb_bytes(billboard_models, georef, content="sprites")


def test_model_content_is_unchanged_by_a_billboard(billboard_models):
    import trimesh

    wood = trimesh.creation.cylinder(radius=0.2, height=6.0, sections=8)
    wood.apply_translation([0, 0, 3.0])
    bare = TreeModel(7, (500000.0, 5400000.0, 300.0), wood, attributes={"height": 12.0})
    dressed = TreeModel(7, (500000.0, 5400000.0, 300.0), wood, attributes={"height": 12.0},
                        billboard=billboard_models[0].billboard)
    georef = Georef(ExportFrame("EPSG:32632"), bare.base)
    assert glb_bytes([bare], georef) == glb_bytes([dressed], georef)
    assert glb_bytes([dressed], georef, content="billboard") != glb_bytes([bare], georef)


def test_tileset_far_tile_draws_billboards(tmp_path, billboard_models):
    import trimesh

    models = []
    for m in billboard_models:
        wood = trimesh.creation.cylinder(radius=0.2, height=10.0, sections=6)
        wood.apply_translation([0, 0, 5.0])
        models.append(TreeModel(m.tree_id, m.base, wood, attributes=m.attributes, billboard=m.billboard))
    out = tmp_path / "tiles"
    write_tileset(models, out, ExportFrame("EPSG:32632"), tile_size_m=20.0)
    ts = json.loads((out / "tileset.json").read_text())
    doc, binary = read_glb(out / "content" / "root.glb")
    assert sum(mat["name"].startswith("billboard_") for mat in doc["materials"]) == len(models)
    # the root box holds every billboard vertex; the error is the distance to the quads' opaque texels
    box = np.array(ts["root"]["boundingVolume"]["box"])
    for m in models:
        p = node_world_positions(doc, binary, m.name)
        assert np.all(np.abs(p - box[:3]) <= box[[3, 7, 11]] + 1e-6)
    errors = [coarse_error(m) for m in models]
    assert ts["root"]["geometricError"] == pytest.approx(max(errors))
    assert 0.0 < max(errors) < 3.0
    # a vertex far from every opaque texel counts
    far = opaque_points(models[0].billboard)
    assert len(far) > 100
    # the child tiles draw the full models
    child = read_glb(out / ts["root"]["children"][0]["content"]["uri"])[0]
    assert not any(mat["name"].startswith("billboard_") for mat in child["materials"])


def test_billboard_glb_passes_the_khronos_validator(tmp_path, billboard_models):
    if shutil.which("node") is None or not (VIEWERS / "node_modules" / "gltf-validator" / "package.json").exists():
        pytest.skip("the Khronos glTF validator is not installed (npm install in tools/viewers)")
    files = [p for p in write_glb(billboard_models, tmp_path / "bb.glb", ExportFrame("EPSG:32632"),
                                  content="billboard") if p.suffix == ".glb"]
    run = subprocess.run(["node", "validate_gltf.mjs", *map(str, files)], cwd=VIEWERS, capture_output=True,
                         text=True, timeout=120)
    reports = [json.loads(line) for line in run.stdout.splitlines() if line.startswith("{")]
    assert len(reports) == 1, run.stderr
    assert reports[0]["errors"] == 0 and reports[0]["warnings"] == 0, reports[0]


# --------------------------------------------------------------------------- the algorithm

@pytest.fixture(scope="module")
def segmented_corner(sample_laz, tmp_path_factory):
    """A 30 m x 30 m corner of the bundled sample, segmented, with a treeID dimension."""
    from conftest import segmented_corner_of

    return segmented_corner_of(sample_laz, tmp_path_factory.mktemp("bbseg"), 30.0)


def test_cli_billboards_on_the_sample(segmented_corner, tmp_path):
    path, labels = segmented_corner
    glb = tmp_path / "bb.glb"
    run = subprocess.run([sys.executable, "-m", "sylva.cli", "--quiet", "billboards", f"--INPUT={path}",
                          f"--OUTPUT={glb}", f"--TILESET={tmp_path / 'tiles'}"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    ids = set(np.unique(labels[labels > 0]).tolist())
    doc, binary = read_glb(glb)
    assert {f"tree_{i}" for i in ids} <= {n.get("name") for n in doc["nodes"]}
    assert glb.stat().st_size <= 40_000 * len(ids)
    assert (tmp_path / "tiles" / "tileset.json").exists()
    # every tree's quads stand on the ground under it (the stem drawn from its DBH) and end at its top
    from sylva.core.io import read_cloud
    from sylva.core.terrain import normalize

    cloud = read_cloud(path)
    height = normalize(cloud).attrs["height"]
    georef = Georef(ExportFrame.from_cloud(cloud), json.loads(glb.with_name("bb.origin.json").read_text())[
        "origin_source"])
    for i in sorted(ids)[:5]:
        src = georef.enu_to_source(node_world_positions(doc, binary, f"tree_{i}"))
        pts = cloud.xyz[labels == i]
        ground = np.median(pts[:, 2] - height[labels == i])
        assert src[:, 2].min() == pytest.approx(ground, abs=0.3) and src[:, 2].max() <= pts[:, 2].max() + 0.5


@pytest.mark.qgis
def test_processing_billboards(sylva_provider, segmented_corner, tmp_path):
    import processing

    path, labels = segmented_corner
    out = tmp_path / "bb.glb"
    result = processing.run("sylva:billboards", {"INPUT": str(path), "OUTPUT": str(out), "TEXTURE_PX": 64})
    assert Path(result["OUTPUT"]) == out and out.exists()
    doc, _ = read_glb(out)
    n = len(np.unique(labels[labels > 0]))
    assert sum(1 for node in doc["nodes"] if node.get("name", "").startswith("tree_")) == n
    assert all(im["mimeType"] == "image/png" for im in doc["images"])


def test_cli_billboards_textured_from_a_street_level_photo(segmented_corner, tmp_path):
    """IMAGE + CAMERA: a photo taken from 40 m south of the corner, looking north, colours the billboards."""
    from PIL import Image

    from sylva.core.io import read_cloud

    path, labels = segmented_corner
    cloud = read_cloud(path)
    centre = np.array([cloud.xyz[:, 0].mean(), cloud.xyz[:, 1].min() - 40.0, cloud.xyz[:, 2].mean()])
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])   # x east, y down, z north (forward)
    camera = {"K": [[200.0, 0.0, 200.0], [0.0, 200.0, 200.0], [0.0, 0.0, 1.0]], "R": R.tolist(),
              "t": (-R @ centre).tolist()}
    (tmp_path / "cam.json").write_text(json.dumps(camera))
    photo = np.zeros((400, 400, 3), np.uint8)
    photo[:] = (200, 40, 30)                                              # a red world
    Image.fromarray(photo).save(tmp_path / "photo.png")
    glb = tmp_path / "bb.glb"
    run = subprocess.run([sys.executable, "-m", "sylva.cli", "--quiet", "billboards", f"--INPUT={path}",
                          f"--IMAGE={tmp_path / 'photo.png'}", f"--CAMERA={tmp_path / 'cam.json'}",
                          f"--OUTPUT={glb}"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    doc, _ = read_glb(glb)
    trees = [n for n in doc["nodes"] if n.get("name", "").startswith("tree_")]
    assert trees and all(n["extras"]["bb_texture"] == "camera" for n in trees)
    bad = subprocess.run([sys.executable, "-m", "sylva.cli", "--quiet", "billboards", f"--INPUT={path}",
                          f"--IMAGE={tmp_path / 'photo.png'}", f"--CAMERA={tmp_path / 'photo.png'}",
                          f"--OUTPUT={tmp_path / 'x.glb'}"], capture_output=True, text=True)
    assert bad.returncode == 1 and "not a camera file" in bad.stderr and not (tmp_path / "x.glb").exists()
