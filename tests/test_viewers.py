"""The 3D exports checked with real tools.

* Khronos glTF validator (npm ``gltf-validator``): every GLB Sylva writes has no error and no warning;
* loaders.gl (npm ``@loaders.gl/3d-tiles``) loads the tileset and parses every tile's content in Node;
* CesiumJS (npm ``cesium``) in headless Chromium (Debian ``chromium``, SwiftShader WebGL) renders
  the tileset; the screenshot has tree pixels that differ from the background;
* CityGML 2.0 and 3.0 validate against the official CityGML / GML XSDs shipped in citygml4j's jar
  (Maven Central ``org.citygml4j:citygml4j-xml:3.0.0``; ``org.citygml4j:citygml4j:2.12.0`` has the 2.0 ones).

Set-up (once): ``cd tools/viewers && npm install``; ``apt-get install -y chromium``;
``mvn -q dependency:get -Dartifact=org.citygml4j:citygml4j-xml:3.0.0 -Dtransitive=false``.  Each test skips with the
reason when its tool is missing.
"""
import base64
import functools
import glob
import http.server
import importlib.util
import io
import json
import os
import shutil
import subprocess
import threading
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from pyproj import CRS

from sylva.core.export import ExportFrame, write_citygml, write_glb, write_tileset

ROOT = Path(__file__).resolve().parents[1]
VIEWERS = ROOT / "tools" / "viewers"
_spec = importlib.util.spec_from_file_location("_sylva_bench_export", ROOT / "benchmarks" / "export.py")
_bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_bench)

CUSTOM_TM = CRS.from_proj4("+proj=tmerc +lat_0=0 +lon_0=10.7 +k=0.9999 +x_0=300000 +y_0=-4500000 "
                           "+ellps=GRS80 +units=m +no_defs").to_wkt()
ENGINEERING = ('ENGCRS["plot frame",EDATUM["plot 7 pegs"],CS[Cartesian,2],'
               'AXIS["x",east,LENGTHUNIT["metre",1]],AXIS["y",north,LENGTHUNIT["metre",1]]]')
BACKGROUND = (40, 90, 200)  # cesium_view.html's background colour


def _need_node_package(name):
    if shutil.which("node") is None:
        pytest.skip("node is not installed (apt-get install nodejs npm)")
    if not (VIEWERS / "node_modules" / name / "package.json").exists():
        pytest.skip(f"npm package {name} is missing: run `npm install` in tools/viewers")


def _node(script, *args, timeout=180):
    return subprocess.run(["node", script, *map(str, args)], cwd=VIEWERS, capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture(scope="module")
def models():
    return _bench.synthetic_models(9, seed=5, nodes=50, unique=3)


@pytest.fixture(scope="module")
def tileset(tmp_path_factory, models):
    folder = tmp_path_factory.mktemp("tiles") / "tileset"
    write_tileset(models, folder, ExportFrame("EPSG:32632"), tile_size_m=12.0)
    return folder


class _Server:
    """A static file server on 127.0.0.1 that also records one POSTed JSON result."""

    def __init__(self, directory):
        self.result = {}
        outer = self

        class Handler(http.server.SimpleHTTPRequestHandler):
            def do_POST(self):
                n = int(self.headers.get("Content-Length", 0))
                outer.result.update(json.loads(self.rfile.read(n) or b"{}"))
                self.send_response(200)
                self.end_headers()

            def log_message(self, *a):
                pass

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0),
                                                     functools.partial(Handler, directory=str(directory)))
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()


def test_glb_files_pass_the_khronos_validator(tmp_path, models, tileset):
    _need_node_package("gltf-validator")
    files = []
    for name, crs, origin, unit in (("utm", "EPSG:32632", (500000.0, 5400000.0, 300.0), 1.0),
                                    ("feet", "EPSG:2994", (4200000.0, 900000.0, 1000.0), 0.3048),
                                    ("wkt", CUSTOM_TM, (300500.0, 900800.0, 200.0), 1.0),
                                    ("local", ENGINEERING, (100.0, 100.0, 0.0), 1.0)):
        ms = _bench.synthetic_models(4, seed=2, origin=origin, unit_m=unit, nodes=40, unique=2)
        files += [p for p in write_glb(ms, tmp_path / f"{name}.glb", ExportFrame(crs)) if p.suffix == ".glb"]
    per_tree = tmp_path / "per_tree"
    per_tree.mkdir()
    files += write_glb(models[:2], per_tree, ExportFrame("EPSG:32632"), per_tree=True, sidecars=False)
    files += sorted((tileset / "content").glob("*.glb"))
    run = _node("validate_gltf.mjs", *files)
    reports = [json.loads(line) for line in run.stdout.splitlines() if line.startswith("{")]
    assert len(reports) == len(files), run.stderr
    for r in reports:
        assert r["errors"] == 0, r
        assert r["warnings"] == 0, r
    assert run.returncode == 0


def test_tileset_traverses_in_loaders_gl(tileset):
    _need_node_package("@loaders.gl/3d-tiles")
    server = _Server(tileset)
    try:
        run = _node("traverse_tileset.mjs", server.url + "/tileset.json")
    finally:
        server.close()
    out = json.loads(run.stdout.strip().splitlines()[-1]) if run.stdout.strip() else {}
    assert run.returncode == 0 and out.get("errors") == [], run.stdout + run.stderr
    n_tiles = 1 + len(json.loads((tileset / "tileset.json").read_text())["root"]["children"])
    assert out["tiles"] == out["contents"] == n_tiles
    # a sylva_root node per tile, and every tree twice (coarse in the parent, full in a child)
    assert out["nodes"] == n_tiles + 2 * 9 and out["triangles"] > 1000


def _chromium():
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if shutil.which(name):
            return shutil.which(name)
    return None


def test_cesium_renders_the_trees_headless(tmp_path, tileset, models):
    _need_node_package("cesium")
    browser = _chromium()
    if browser is None:
        pytest.skip("chromium is not installed (apt-get install -y chromium)")
    site = tmp_path / "site"
    site.mkdir()
    (site / "Cesium").symlink_to(VIEWERS / "node_modules" / "cesium" / "Build" / "Cesium")
    (site / "data").symlink_to(tileset)
    shutil.copy(VIEWERS / "cesium_view.html", site / "index.html")
    server = _Server(site)
    log = open(tmp_path / "chromium.log", "w")
    proc = subprocess.Popen([browser, "--headless=new", "--no-sandbox", "--disable-gpu", "--use-gl=angle",
                             "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                             "--disable-background-networking", "--disable-dev-shm-usage", "--no-first-run",
                             "--disable-extensions", "--window-size=640,480",
                             f"--user-data-dir={tmp_path / 'profile'}", server.url + "/index.html"],
                            stdout=subprocess.DEVNULL, stderr=log)
    try:
        t0 = time.time()
        while not server.result and time.time() - t0 < 150 and proc.poll() is None:
            time.sleep(0.25)
    finally:
        proc.terminate()
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
        server.close()
        log.close()
    result = server.result
    if not result:
        tail = (tmp_path / "chromium.log").read_text()[-1500:]
        pytest.fail(f"CesiumJS posted no result within 150 s (chromium exit {proc.returncode}); log tail: {tail}")
    assert result["status"] == "ok", result.get("message")
    assert result["tiles"] >= 2
    # CesiumJS reaches every tree's attributes through EXT_mesh_features / EXT_structural_metadata
    seen = {}
    for f in result["features"]:
        seen.setdefault(f["tree_id"], set()).add((f["species"], round(f["height"], 3)))
    assert sorted(seen) == [m.tree_id for m in models]
    for m in models:
        assert seen[m.tree_id] == {(m.attributes["species"], m.attributes["height"])}
    Image = pytest.importorskip("PIL.Image", reason="Pillow is needed to decode the screenshot")
    png = base64.b64decode(result["png"].split(",", 1)[1])
    (tmp_path / "cesium.png").write_bytes(png)
    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
    differs = np.abs(img - np.array(BACKGROUND)).sum(axis=2) > 40
    frac = differs.mean()
    assert 0.002 < frac < 0.6, f"{frac:.4f} of the pixels differ from the background (screenshot {tmp_path / 'cesium.png'})"
    rows, cols = np.nonzero(differs)
    # the trees are in the middle of the view, not a frame or an overlay at the edge
    assert 0.15 * img.shape[0] < rows.mean() < 0.85 * img.shape[0]
    assert 0.15 * img.shape[1] < cols.mean() < 0.85 * img.shape[1]


def _citygml4j_jars():
    """citygml4j jars that ship the official CityGML XSDs (Maven Central)."""
    env = os.environ.get("SYLVA_CITYGML4J_JAR")
    jars = [Path(env)] if env and Path(env).exists() else []
    m2 = Path.home() / ".m2" / "repository" / "org" / "citygml4j"
    jars += [Path(p) for p in sorted(glob.glob(str(m2 / "citygml4j-xml" / "3.*" / "citygml4j-xml-3.*.jar")))]
    jars += [Path(p) for p in sorted(glob.glob(str(m2 / "citygml4j" / "2.*" / "citygml4j-2.*.jar")))]
    return jars


_VEG_NS = {"2.0": "http://www.opengis.net/citygml/vegetation/2.0",
           "3.0": "http://www.opengis.net/citygml/vegetation/3.0"}


@pytest.fixture(scope="module")
def citygml_schemas(tmp_path_factory):
    """{version: lxml XMLSchema} for the CityGML versions whose XSDs a citygml4j jar ships."""
    from lxml import etree

    schemas = {}
    for k, jar in enumerate(_citygml4j_jars()):
        root = tmp_path_factory.mktemp(f"xsd{k}")
        with zipfile.ZipFile(jar) as z:
            z.extractall(root, [n for n in z.namelist() if n.startswith("org/citygml4j/schemas/")])
        for veg in sorted(root.rglob("vegetation.xsd")):
            text = veg.read_text(encoding="utf-8", errors="replace")
            version = next((v for v, ns in _VEG_NS.items() if f'targetNamespace="{ns}"' in text), None)
            if version is None or version in schemas:
                continue
            gen = "http://www.opengis.net/citygml/generics/" + version
            wrapper = veg.parent / "_sylva_all.xsd"
            wrapper.write_text(
                '<xs:schema xmlns:xs="http://www.w3.org/2001/XMLSchema" targetNamespace="urn:sylva:wrapper">'
                f'<xs:import namespace="{_VEG_NS[version]}" schemaLocation="vegetation.xsd"/>'
                f'<xs:import namespace="{gen}" schemaLocation="generics.xsd"/></xs:schema>')
            schemas[version] = etree.XMLSchema(etree.parse(str(wrapper)))
    return schemas


def _schema(schemas, version):
    if version not in schemas:
        pytest.skip(f"CityGML {version} XSDs not found: run `mvn -q dependency:get "
                    f"-Dartifact=org.citygml4j:citygml4j-xml:3.0.0 -Dtransitive=false` "
                    f"(or set SYLVA_CITYGML4J_JAR to a citygml4j jar)")
    return schemas[version]


@pytest.mark.parametrize("version", ["2.0", "3.0"])
@pytest.mark.parametrize("options", [{}, {"implicit": True}, {"leaves": True}])
def test_citygml_validates_against_the_official_schema(tmp_path, models, citygml_schemas, options, version):
    from lxml import etree

    schema = _schema(citygml_schemas, version)
    path = tmp_path / "trees.gml"
    write_citygml(models[:3], path, ExportFrame("EPSG:32632"), version=version, **options)
    doc = etree.parse(str(path))
    ok = schema.validate(doc)
    assert ok, "\n".join(str(e) for e in list(schema.error_log)[:10])


@pytest.mark.parametrize("version", ["2.0", "3.0"])
def test_citygml_schema_rejects_a_broken_file(tmp_path, models, citygml_schemas, version):
    """The schema really checks: species moved behind the geometry violates the vegetation sequence."""
    from lxml import etree

    from sylva.core.export.citygml import NS3

    citygml_schema = _schema(citygml_schemas, version)
    from sylva.core.export.citygml import NS

    ns = NS if version == "2.0" else NS3
    path = tmp_path / "bad.gml"
    write_citygml(models[:1], path, ExportFrame("EPSG:32632"), version=version)
    doc = etree.parse(str(path))
    assert citygml_schema.validate(doc)
    svo = doc.find(".//veg:SolitaryVegetationObject", ns)
    species = svo.find("veg:species", ns)
    svo.remove(species)
    svo.insert(1, species)
    assert not citygml_schema.validate(doc)
    assert "SCHEMAV_ELEMENT_CONTENT" in str(citygml_schema.error_log)
