"""3D exports: GLB structure and georeferencing round trip, 3D Tiles bounds and LOD, OBJ, CityGML, bad input."""
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from pyproj import CRS

from sylva.core.errors import CRSError, InputError
from sylva.core.export import ExportFrame, Georef, TreeModel, write_citygml, write_glb, write_obj, write_tileset
from sylva.core.export.gltf import accessor_array, glb_bytes, node_world_positions, read_glb

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("_sylva_bench_export", ROOT / "benchmarks" / "export.py")
_bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_bench)

CUSTOM_TM = CRS.from_proj4("+proj=tmerc +lat_0=0 +lon_0=10.7 +k=0.9999 +x_0=300000 +y_0=-4500000 "
                           "+ellps=GRS80 +units=m +no_defs").to_wkt()
ENGINEERING = ('ENGCRS["plot frame",EDATUM["plot 7 pegs"],CS[Cartesian,2],'
               'AXIS["x",east,LENGTHUNIT["metre",1]],AXIS["y",north,LENGTHUNIT["metre",1]]]')
CASES = {  # crs, origin (CRS units), metres per unit
    "utm": ("EPSG:32632", (500000.0, 5400000.0, 300.0), 1.0),
    "feet": ("EPSG:2994", (4200000.0, 900000.0, 1000.0), 0.3048),
    "wkt": (CUSTOM_TM, (300500.0, 900800.0, 200.0), 1.0),
    "geoid": ("EPSG:32632+5773", (500000.0, 5400000.0, 300.0), 1.0),   # UTM + EGM96 heights
}


def models_for(case, n=5, **kw):
    crs, origin, unit = CASES[case]
    return _bench.synthetic_models(n, seed=3, origin=origin, unit_m=unit, nodes=40, unique=3, **kw), ExportFrame(crs)


@pytest.fixture(scope="module")
def utm():
    return models_for("utm")


def _georef_from_file(extras):
    """A Georef rebuilt only from what the file says (CRS WKT, origin, units)."""
    from sylva.core.cloud import Units

    geo = extras["georeference"]
    units = Units(**geo["units"])
    return Georef(ExportFrame(geo["crs_wkt"], units), geo["origin_source"])


@pytest.mark.parametrize("case", sorted(CASES))
def test_glb_round_trip_to_source_crs_within_1cm(tmp_path, case):
    models, frame = models_for(case)
    out = tmp_path / "trees.glb"
    write_glb(models, out, frame)
    doc, binary = read_glb(out)
    g = _georef_from_file(doc["asset"]["extras"])
    for m in models:
        node = next(n for n in doc["nodes"] if n["name"] == m.name)
        base_back = g.enu_to_source(np.array([node["translation"]]))[0]
        scale = np.array([g.units.horizontal_m] * 2 + [g.units.vertical_m])
        assert np.abs((base_back - m.base) * scale).max() < 0.01
        enu = node_world_positions(doc, binary, m.name)          # GLB -> ENU (z-up)
        ecef = g.enu_to_ecef_points(enu)                          # -> ECEF
        src = g.geodetic_to_source(g.ecef_to_geodetic(ecef))      # -> source CRS
        wood = m.wood.vertices[np.unique(m.wood.faces)]
        expected = m.base + wood / scale
        got = src[:len(wood)]
        assert np.abs((got - expected) * scale).max() < 0.01, case
        # the model's base vertex (its lowest ring centre's height) lands on the ground z
        assert abs((got[:, 2].min() - expected[:, 2].min()) * scale[2]) < 0.01


def test_glb_structure(tmp_path, utm):
    models, frame = utm
    out = tmp_path / "tile.glb"
    paths = write_glb(models, out, frame)
    assert {p.name for p in paths} == {"tile.glb", "tile.prj", "tile.origin.json"}
    assert CRS.from_wkt((tmp_path / "tile.prj").read_text()).equals(CRS("EPSG:32632"), ignore_axis_order=True)
    sidecar = json.loads((tmp_path / "tile.origin.json").read_text())
    assert sidecar["crs_epsg"] == 32632 and len(sidecar["origin_lon_lat_h"]) == 3
    data = out.read_bytes()
    assert data[:4] == b"glTF" and int.from_bytes(data[8:12], "little") == len(data)
    doc, binary = read_glb(data)
    assert doc["asset"]["version"] == "2.0"
    root = doc["nodes"][0]
    assert root["name"] == "sylva_root" and root["matrix"] == [1, 0, 0, 0, 0, 0, -1, 0, 0, 1, 0, 0, 0, 0, 0, 1]
    assert root["extras"]["georeference"]["crs_epsg"] == 32632
    names = [doc["nodes"][c]["name"] for c in root["children"]]
    assert names == [m.name for m in models]
    for m in models:
        node = next(n for n in doc["nodes"] if n["name"] == m.name)
        assert node["extras"]["tree_id"] == m.tree_id and node["extras"]["species"] == m.attributes["species"]
        assert node["extras"]["height"] == pytest.approx(m.attributes["height"])
    for view in doc["bufferViews"]:
        assert view["byteOffset"] % 8 == 0 and view["byteOffset"] + view["byteLength"] <= len(binary)
    for acc in doc["accessors"]:
        if "min" in acc:
            a = accessor_array(doc, binary, doc["accessors"].index(acc))
            assert a.min(axis=0).tolist() == acc["min"] and a.max(axis=0).tolist() == acc["max"]
    mats = {mt["name"]: mt for mt in doc["materials"]}
    assert mats["bark"]["pbrMetallicRoughness"]["baseColorFactor"][0] > mats["bark"]["pbrMetallicRoughness"]["baseColorFactor"][2]
    leaf = mats["leaves_ovate"]
    assert leaf["alphaMode"] == "MASK" and leaf["doubleSided"] is True
    img = doc["images"][doc["textures"][leaf["pbrMetallicRoughness"]["baseColorTexture"]["index"]]["source"]]
    v = doc["bufferViews"][img["bufferView"]]
    assert binary[v["byteOffset"]:v["byteOffset"] + 8] == b"\x89PNG\r\n\x1a\n"
    # leaf texture v is flipped for glTF
    m0 = models[0]
    mesh = doc["meshes"][next(n for n in doc["nodes"] if n["name"] == m0.name)["mesh"]]
    leaf_prim = next(p for p in mesh["primitives"] if "TEXCOORD_0" in p["attributes"])
    uv = accessor_array(doc, binary, leaf_prim["attributes"]["TEXCOORD_0"])
    assert np.allclose(uv[:, 1], 1.0 - m0.leaves.uvs[np.unique(m0.leaves.faces), 1], atol=1e-6)


def test_glb_structural_metadata_table(utm):
    models, frame = utm
    g = Georef(frame, models[0].base)
    doc, binary = read_glb(glb_bytes(models, g))
    assert doc["extensionsUsed"] == ["EXT_mesh_features", "EXT_structural_metadata"]
    meta = doc["extensions"]["EXT_structural_metadata"]
    props = meta["schema"]["classes"]["tree"]["properties"]
    table = meta["propertyTables"][0]
    assert table["count"] == len(models) and props["dbh"]["componentType"] == "FLOAT64"

    def column(name):
        v = doc["bufferViews"][table["properties"][name]["values"]]
        raw = binary[v["byteOffset"]:v["byteOffset"] + v["byteLength"]]
        if props[name]["type"] == "STRING":
            o = doc["bufferViews"][table["properties"][name]["stringOffsets"]]
            offs = np.frombuffer(binary, "<u4", len(models) + 1, o["byteOffset"])
            return [raw[offs[i]:offs[i + 1]].decode() for i in range(len(models))]
        return np.frombuffer(raw, "<f8" if props[name]["componentType"] == "FLOAT64" else "<i4").tolist()

    assert column("tree_id") == [m.tree_id for m in models]
    assert column("dbh") == [m.attributes["dbh"] for m in models]
    assert column("species") == [m.attributes["species"] for m in models]
    # every vertex of tree i carries feature id i
    for i, m in enumerate(models):
        node = next(n for n in doc["nodes"] if n["name"] == m.name)
        for p in doc["meshes"][node["mesh"]]["primitives"]:
            ids = accessor_array(doc, binary, p["attributes"]["_FEATURE_ID_0"])
            assert np.all(ids == i)
            fid = p["extensions"]["EXT_mesh_features"]["featureIds"][0]
            assert fid == {"featureCount": len(models), "attribute": 0, "propertyTable": 0}


def test_outputs_are_deterministic_and_atomic(tmp_path, utm):
    models, frame = utm
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir(), b.mkdir()
    for d in (a, b):
        write_glb(models, d / "t.glb", frame)
        write_obj(models, d / "t.obj", frame)
        write_citygml(models, d / "t.gml", frame)
        write_tileset(models, d / "tiles", frame)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert len(files) > 10
    for rel in files:
        assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel
    assert not [p for p in tmp_path.rglob("*.tmp")]


def test_glb_per_tree(tmp_path, utm):
    models, frame = utm
    paths = write_glb(models, tmp_path, frame, per_tree=True, sidecars=False)
    assert [p.name for p in paths] == [f"tree_{m.tree_id}.glb" for m in models]
    doc, _ = read_glb(paths[0])
    node = next(n for n in doc["nodes"] if n["name"] == models[0].name)
    assert np.allclose(node["translation"], 0.0, atol=1e-6)            # origin at the tree base
    assert np.allclose(doc["asset"]["extras"]["georeference"]["origin_source"], models[0].base)
    with pytest.raises(InputError, match="must be an existing folder"):
        write_glb(models, tmp_path / "nope", frame, per_tree=True)


def _box_contains(box, pts, tol=1e-6):
    c = np.array(box[:3])
    axes = np.array(box[3:]).reshape(3, 3)
    local = (pts - c) @ np.linalg.inv(axes)
    return np.abs(local).max() <= 1.0 + tol


def test_tileset_bounds_lod_and_transform(tmp_path):
    models, frame = models_for("utm", n=12)
    folder = tmp_path / "tiles"
    write_tileset(models, folder, frame, tile_size_m=15.0)
    ts = json.loads((folder / "tileset.json").read_text())
    root = ts["root"]
    assert ts["asset"]["version"] == "1.1"
    g = Georef(frame, ts["extras"]["georeference"]["origin_source"])
    assert np.allclose(np.array(root["transform"]).reshape(4, 4).T, g.enu_to_ecef)
    assert len(root["children"]) > 1 and root["refine"] == "REPLACE"
    assert ts["geometricError"] >= root["geometricError"] > 0.0
    assert all(c["geometricError"] == 0.0 for c in root["children"])
    seen = []
    child_tris = 0
    for tile in [root] + root["children"]:
        doc, binary = read_glb(folder / tile["content"]["uri"])
        for node in doc["nodes"][1:]:
            pts = node_world_positions(doc, binary, node["name"])
            assert _box_contains(tile["boundingVolume"]["box"], pts), tile["content"]["uri"]
            assert _box_contains(root["boundingVolume"]["box"], pts)
            if tile is not root:
                seen.append(node["name"])
                child_tris += sum(doc["accessors"][p["indices"]]["count"] // 3
                                  for p in doc["meshes"][node["mesh"]]["primitives"])
    assert sorted(seen) == sorted(m.name for m in models)
    doc, _ = read_glb(folder / root["content"]["uri"])
    root_tris = sum(doc["accessors"][p["indices"]]["count"] // 3 for m in doc["meshes"] for p in m["primitives"])
    assert root_tris < child_tris / 2                                  # the parent is the coarse level
    # the coarse error is a real distance: positive and below the largest tree's size
    assert root["geometricError"] < max(m.attributes["height"] + m.attributes["crown_diameter"] for m in models)


def test_tileset_box_is_tight(tmp_path):
    models, frame = models_for("utm", n=3)
    write_tileset(models, tmp_path / "t", frame)
    ts = json.loads((tmp_path / "t" / "tileset.json").read_text())
    child = ts["root"]["children"][0]
    doc, binary = read_glb(tmp_path / "t" / child["content"]["uri"])
    pts = np.concatenate([node_world_positions(doc, binary, n["name"]) for n in doc["nodes"][1:]])
    box = np.array(child["boundingVolume"]["box"])
    lo, hi = box[:3] - box[[3, 7, 11]], box[:3] + box[[3, 7, 11]]
    assert np.allclose(pts.min(axis=0), lo + 0.01, atol=1e-3) and np.allclose(pts.max(axis=0), hi - 0.01, atol=1e-3)


def test_obj_offsets_and_materials(tmp_path):
    models, frame = models_for("feet", n=3)
    paths = write_obj(models, tmp_path / "trees.obj", frame)
    names = {p.name for p in paths}
    assert {"trees.obj", "trees.mtl", "trees.prj", "trees.offset.txt", "trees.origin.json"} <= names
    assert any(n.startswith("trees_leaf_") and n.endswith(".png") for n in names)
    origin = np.array((tmp_path / "trees.offset.txt").read_text().split(), float)
    lines = (tmp_path / "trees.obj").read_text().splitlines()
    v = np.array([ln.split()[1:] for ln in lines if ln.startswith("v ")], float)
    vt = [ln for ln in lines if ln.startswith("vt ")]
    nverts = sum(len(m.wood.vertices) + len(m.leaves.vertices) for m in models)
    assert len(v) == nverts and len(vt) == sum(len(m.leaves.uvs) for m in models)
    assert np.abs(v).max() < 500                                         # small numbers: relative to the origin
    m0 = models[0]
    expected = m0.base + m0.wood.vertices / 0.3048                      # feet
    assert np.abs((v[:len(m0.wood.vertices)] + origin - expected) * 0.3048).max() < 1e-3
    faces = [ln for ln in lines if ln.startswith("f ")]
    assert len(faces) == sum(len(m.wood.faces) + len(m.leaves.faces) for m in models)
    mtl = (tmp_path / "trees.mtl").read_text()
    assert "newmtl bark" in mtl and "map_d trees_leaf_" in mtl
    assert [ln for ln in lines if ln.startswith("o ")] == [f"o {m.name}" for m in models]


def test_citygml_content(tmp_path):
    from lxml import etree

    from sylva.core.export.citygml import NS

    models, frame = models_for("utm", n=4)
    write_citygml(models, tmp_path / "trees.gml", frame)
    doc = etree.parse(str(tmp_path / "trees.gml"))
    svos = doc.findall(".//veg:SolitaryVegetationObject", NS)
    assert [s.get(f"{{{NS['gml']}}}id") for s in svos] == [m.name for m in models]
    for s, m in zip(svos, models):
        assert s.findtext("veg:species", namespaces=NS) == m.attributes["species"]
        assert float(s.findtext("veg:height", namespaces=NS)) == m.attributes["height"]
        assert s.find("veg:height", NS).get("uom") == "m"
        assert float(s.findtext("veg:trunkDiameter", namespaces=NS)) == m.attributes["dbh"]
        ms = s.find("veg:lod2Geometry/gml:MultiSurface", NS)
        assert ms.get("srsName") == "EPSG:32632"
        polys = ms.findall("gml:surfaceMember/gml:Polygon", NS)
        assert len(polys) == len(m.wood.faces)
        ring = np.array(polys[0].findtext(".//gml:posList", namespaces=NS).split(), float).reshape(4, 3)
        assert np.allclose(ring[0], ring[3])
        assert np.abs(ring[:3] - (m.base + m.wood.vertices[m.wood.faces[0]])).max() < 1e-3
        assert s.find("veg:lod1Geometry/gml:MultiSurface", NS) is not None
        ints = {a.get("name"): a.findtext("gen:value", namespaces=NS) for a in s.findall("gen:intAttribute", NS)}
        assert ints["tree_id"] == str(m.tree_id)
    env = doc.find("gml:boundedBy/gml:Envelope", NS)
    lo = np.array(env.findtext("gml:lowerCorner", namespaces=NS).split(), float)
    assert np.all(lo <= np.min([m.base for m in models], axis=0) + 1.0)


def test_citygml_implicit_reuses_prototypes(tmp_path):
    from lxml import etree

    from sylva.core.export.citygml import NS

    models, frame = models_for("utm", n=6)                              # 3 distinct meshes
    write_citygml(models, tmp_path / "i.gml", frame, implicit=True)
    doc = etree.parse(str(tmp_path / "i.gml"))
    protos = doc.findall(".//core:relativeGMLGeometry/gml:MultiSurface", NS)
    refs = doc.findall(".//core:relativeGMLGeometry[@xlink:href]", NS)
    assert len(protos) == 3 and len(refs) == 3
    pts = doc.findall(".//core:referencePoint/gml:Point/gml:pos", NS)
    assert np.allclose([np.array(p.text.split(), float) for p in pts], [m.base for m in models])


def test_citygml_3_content(tmp_path):
    from lxml import etree

    from sylva.core.export.citygml import NS3

    models, frame = models_for("feet", n=2)
    write_citygml(models, tmp_path / "t3.gml", frame, version="3.0")
    doc = etree.parse(str(tmp_path / "t3.gml"))
    assert doc.getroot().tag == f"{{{NS3['core']}}}CityModel"
    svos = doc.findall(".//veg:SolitaryVegetationObject", NS3)
    assert len(svos) == 2
    m = models[0]
    ms = svos[0].find("core:lod2MultiSurface/gml:MultiSurface", NS3)
    assert ms.get("srsName") == "EPSG:2994"
    ring = np.array(ms.findtext(".//gml:posList", namespaces=NS3).split(), float).reshape(4, 3)
    assert np.abs(ring[:3] - (m.base + m.wood.vertices[m.wood.faces[0]] / 0.3048)).max() < 2e-3   # feet
    ids = [e.get(f"{{{NS3['gml']}}}id") for e in doc.iter() if e.get(f"{{{NS3['gml']}}}id")]
    assert len(ids) == len(set(ids)) > sum(len(x.wood.faces) for x in models)
    names = {g.findtext("gen:name", namespaces=NS3) for g in svos[0].findall("core:genericAttribute/*", NS3)}
    assert {"tree_id", "height", "species"} <= names
    with pytest.raises(InputError, match="version"):
        write_citygml(models, tmp_path / "x.gml", frame, version="1.0")


def test_citygml_compound_crs_srs_name(tmp_path):
    import warnings

    from lxml import etree

    from sylva.core.export.citygml import NS

    models, _ = models_for("utm", n=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        write_citygml(models, tmp_path / "c.gml", ExportFrame("EPSG:32632+5773"))
    env = etree.parse(str(tmp_path / "c.gml")).find("gml:boundedBy/gml:Envelope", NS)
    assert env.get("srsName") == "urn:ogc:def:crs,crs:EPSG::32632,crs:EPSG::5773"


def test_local_engineering_crs(tmp_path, utm):
    models, _ = utm
    frame = ExportFrame(ENGINEERING)
    write_glb(models, tmp_path / "local.glb", frame)
    doc, binary = read_glb(tmp_path / "local.glb")
    geo = doc["asset"]["extras"]["georeference"]
    assert geo["frame"] == "local grid" and "origin_lon_lat_h" not in geo
    node = next(n for n in doc["nodes"] if n["name"] == models[0].name)
    assert np.allclose(node["translation"], models[0].base - geo["origin_source"])
    write_obj(models, tmp_path / "local.obj", frame)
    with pytest.raises(CRSError, match="no geodetic datum"):
        write_tileset(models, tmp_path / "tiles", frame)
    with pytest.raises(CRSError, match="no geodetic datum"):
        write_tileset(models, tmp_path / "tiles", ExportFrame(None))


def test_bad_input_messages(tmp_path, utm):
    models, frame = utm
    empty = TreeModel(99, models[0].base, trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int)), None, {})
    for writer, target in ((write_glb, "e.glb"), (write_obj, "e.obj"), (write_citygml, "e.gml"),
                           (write_tileset, "tiles")):
        with pytest.raises(InputError, match="tree 99 has an empty mesh"):
            writer(models + [empty], tmp_path / target, frame)
    with pytest.raises(InputError, match="no trees"):
        write_glb([], tmp_path / "x.glb", frame)
    with pytest.raises(InputError, match="occurs twice"):
        write_glb([models[0], models[0]], tmp_path / "x.glb", frame)
    with pytest.raises(InputError, match="tree 5: base"):
        TreeModel(5, [1.0, np.nan, 2.0], models[0].wood)
    with pytest.raises(InputError, match="does not exist"):
        write_glb(models, tmp_path / "missing" / "x.glb", frame)
    with pytest.raises(CRSError, match="geographic"):
        write_glb(models, tmp_path / "x.glb", ExportFrame("EPSG:4326"))
    assert not list(tmp_path.rglob("*.tmp")) and not (tmp_path / "x.glb").exists()


def test_wood_only_tree_and_missing_attributes(tmp_path, utm):
    models, frame = utm
    bare = TreeModel(42, models[0].base + (3, 3, 0), models[0].wood, None, {"height": None, "species": None})
    doc, binary = read_glb(glb_bytes([models[1], bare], Georef(frame, models[1].base)))
    props = doc["extensions"]["EXT_structural_metadata"]["schema"]["classes"]["tree"]["properties"]
    assert props["height"]["noData"] == -9999 and props["species"]["noData"] == ""
    node = next(n for n in doc["nodes"] if n["name"] == "tree_42")
    assert len(doc["meshes"][node["mesh"]]["primitives"]) == 1
