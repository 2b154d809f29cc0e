"""LAS/LAZ and text point-cloud I/O (sylva.core.io), on real files in tmp_path.

Every source file here is written by laspy itself (the reference), filled
with seeded random raw records, so a lossless round trip through
read_las/write_las must reproduce it byte for byte.
"""
from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pyproj
import pytest

from sylva.core.cloud import INTERNATIONAL_FOOT, METRE, US_SURVEY_FOOT, PointCloud, Units
from sylva.core.errors import CRSError, EmptyInputError, InputError, SylvaError
from sylva.core.io import (
    LasTemplate,
    las_info,
    read_cloud,
    read_las,
    read_las_chunks,
    read_xyz,
    require_crs,
    units_of,
    write_las,
)

# random raw bytes make NaN floats, on which laspy's extra-bytes statistics warn
pytestmark = pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "als"

VERSION_FORMATS = [(v, f) for v in ("1.2", "1.3", "1.4")
                   for f in laspy.point.dims.VERSION_TO_POINT_FMT[v]]
EXTRA = [
    laspy.ExtraBytesParams("treeID", np.int32, description="tree id, 0 = none"),
    laspy.ExtraBytesParams("height", np.float64),
    laspy.ExtraBytesParams("flag8", np.uint8),
    laspy.ExtraBytesParams("scaled", np.int32, scales=np.array([0.01]), offsets=np.array([5.0])),
    laspy.ExtraBytesParams("normal", "3f4"),
]
UTM12 = pyproj.CRS.from_epsg(26912)


def make_las(path, version="1.4", fmt=6, n=3000, crs=UTM12, extra=True, seed=0,
             evlr=True) -> laspy.LasData:
    """A laspy-written file with random raw records in every dimension."""
    rng = np.random.default_rng(seed)
    header = laspy.LasHeader(version=version, point_format=fmt)
    header.scales = np.array([0.01, 0.01, 0.001])
    header.offsets = np.array([481000.0, 3812000.0, 0.0])
    if extra:
        header.add_extra_dims(EXTRA)
    dtype = header.point_format.dtype()
    array = np.frombuffer(rng.bytes(n * dtype.itemsize), dtype=dtype).copy()
    array["X"] = rng.integers(0, 100_000, n)
    array["Y"] = rng.integers(0, 100_000, n)
    array["Z"] = rng.integers(-5_000, 60_000, n)
    if fmt in (9, 10) and str(path).endswith(".laz"):
        # lazrs 0.8.2 mis-decodes wave packets once the scanner channel changes
        # (laspy alone does not round-trip such a file either): one channel here.
        array["classification_flags"] &= 0b11001111
    header.vlrs.append(laspy.VLR("SylvaTest", 42, "a custom VLR", b"keep me \x00\x01"))
    if crs is not None:
        header.add_crs(crs)
    las = laspy.LasData(header, laspy.ScaleAwarePointRecord(
        array, header.point_format, header.scales, header.offsets))
    if evlr and version == "1.4":
        las.evlrs = laspy.vlrs.vlrlist.VLRList(
            [laspy.VLR("SylvaTest", 43, "an EVLR", b"evlr payload")])
    las.write(str(path))
    return laspy.read(str(path))


def same(a, b) -> bool:
    """Equal arrays, NaN equal to NaN (random raw bytes make NaN floats)."""
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and bool(np.array_equal(
        a, b, equal_nan=a.dtype.kind == "f" and b.dtype.kind == "f"))


def vlr_keys(vlrs, stats=True):
    """VLRs that must survive, as comparable tuples (the LAZ VLR is the codec's).

    With ``stats=False`` the ExtraBytes VLR is compared without its data,
    which holds per-dimension min/max statistics that follow the points."""
    keys = []
    for v in vlrs:
        if v.user_id == "laszip encoded":
            continue
        extra_bytes = (v.user_id, v.record_id) == ("LASF_Spec", 4)
        data = b"" if extra_bytes and not stats else bytes(v.record_data_bytes())
        keys.append((v.user_id, v.record_id, data))
    return keys


def assert_same_file(a: Path, b: Path, index=None):
    """Same header essentials, VLRs, EVLRs, CRS and raw records (optionally ``a[index]``)."""
    la, lb = laspy.read(str(a)), laspy.read(str(b))
    ha, hb = la.header, lb.header
    assert str(ha.version) == str(hb.version)
    assert ha.point_format.id == hb.point_format.id
    assert list(ha.point_format.dimension_names) == list(hb.point_format.dimension_names)
    assert np.array_equal(ha.scales, hb.scales) and np.array_equal(ha.offsets, hb.offsets)
    stats = index is None
    assert vlr_keys(ha.vlrs, stats) == vlr_keys(hb.vlrs, stats)
    assert vlr_keys(la.evlrs or [], stats) == vlr_keys(lb.evlrs or [], stats)
    assert ha.parse_crs() == hb.parse_crs()
    raw_a = la.points.array if index is None else la.points.array[index]
    assert raw_a.tobytes() == lb.points.array.tobytes()
    return la, lb


# ------------------------------------------------------------------ round trips


@pytest.mark.parametrize("suffix", [".las", ".laz"])
@pytest.mark.parametrize("version,fmt", VERSION_FORMATS)
def test_round_trip_every_version_and_format(tmp_path, version, fmt, suffix):
    src = tmp_path / f"src{suffix}"
    las = make_las(src, version, fmt, n=1000, seed=fmt)
    cloud = read_las(src)
    # reader: scaled xyz exactly as laspy computes them, every dimension by name
    assert np.array_equal(cloud.xyz, las.xyz)
    names = [d for d in las.point_format.dimension_names if d not in ("X", "Y", "Z")]
    assert list(cloud.attrs) == names
    for name in names:
        assert same(cloud.attrs[name], las[name]), name
    assert cloud.crs == UTM12 and cloud.units == Units(METRE, METRE)
    assert cloud.source == str(src) and isinstance(cloud.template, LasTemplate)
    # writer: byte-identical records, same header, VLRs, EVLRs and CRS
    out = tmp_path / f"out{suffix}"
    write_las(out, cloud)
    assert_same_file(src, out)
    back = read_las(out)
    assert np.array_equal(back.xyz, cloud.xyz)
    assert back.crs == cloud.crs


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_1_0_and_1_1(tmp_path, suffix):
    """laspy writes 1.1 onwards; a 1.0 file (same layout) is made by patching the
    version byte, reads, and is written back as 1.1 with identical records."""
    src11 = tmp_path / f"v11{suffix}"
    make_las(src11, "1.1", 1, n=500)
    src10 = tmp_path / f"v10{suffix}"
    raw = bytearray(src11.read_bytes())
    assert raw[24:26] == b"\x01\x01"
    raw[25] = 0
    src10.write_bytes(bytes(raw))
    for src, version in ((src11, "1.1"), (src10, "1.0")):
        cloud = read_las(src)
        assert las_info(src).version == version and cloud.crs == UTM12
        assert np.array_equal(cloud.xyz, laspy.read(str(src11)).xyz)
        out = tmp_path / f"out{suffix}"
        write_las(out, cloud)
        assert las_info(out).version == "1.1"
        assert laspy.read(str(out)).points.array.tobytes() == \
            laspy.read(str(src11)).points.array.tobytes()


def test_subset_then_write_keeps_the_kept_points(tmp_path):
    src = tmp_path / "src.laz"
    make_las(src, "1.4", 8)
    cloud = read_las(src)
    keep = cloud.xyz[:, 2] > 20.0
    assert 0 < keep.sum() < len(cloud)
    sub = cloud.subset(keep)
    write_las(tmp_path / "sub.laz", sub)
    _, lb = assert_same_file(src, tmp_path / "sub.laz", index=keep)
    assert lb.header.point_count == keep.sum()
    # header bounds follow the kept points
    assert np.allclose(lb.header.mins, sub.xyz.min(axis=0))
    # index arrays work as well as masks, in the order given
    idx = np.array([5, 3, 2999, 0])
    write_las(tmp_path / "idx.las", cloud.subset(idx))
    assert_same_file(src, tmp_path / "idx.las", index=idx)


def test_extra_tree_id_added_and_read_back(tmp_path):
    src = tmp_path / "src.las"
    make_las(src, "1.2", 1, extra=False)
    cloud = read_las(src)
    tree = np.arange(len(cloud), dtype=np.int32) % 7
    write_las(tmp_path / "out.laz", cloud, extra={"treeID": tree})
    back = read_las(tmp_path / "out.laz")
    assert back.attrs["treeID"].dtype == np.int32
    assert np.array_equal(back.attrs["treeID"], tree)
    for name, values in cloud.attrs.items():
        assert same(back.attrs[name], values), name
    assert np.array_equal(back.xyz, cloud.xyz) and back.crs == UTM12
    # the new dimension comes with an ExtraBytes VLR readers such as lidR understand
    assert las_info(tmp_path / "out.laz").extra_dimensions == ("treeID",)
    # attributes that are not LAS dimensions are written as extra dimensions too
    write_las(tmp_path / "attr.las", cloud.with_attrs(hag=cloud.xyz[:, 2] - 1.5))
    assert np.array_equal(read_las(tmp_path / "attr.las").attrs["hag"], cloud.xyz[:, 2] - 1.5)


def test_changed_attributes_are_written(tmp_path):
    src = tmp_path / "src.las"
    make_las(src, "1.4", 7)
    cloud = read_las(src)
    cls = cloud.attrs["classification"].copy()
    cls[::2] = 2
    tree = np.where(cloud.xyz[:, 2] > 10, 17, 0).astype(np.int32)
    changed = cloud.with_attrs(classification=cls, treeID=tree)
    changed.attrs["synthetic"][:] = 1  # in place, through the attrs dict
    changed.xyz[:10, 0] += 1.0  # moved points
    write_las(tmp_path / "out.las", changed)
    # the source cloud's template records are never modified by a write
    assert cloud.template.array.tobytes() == laspy.read(str(src)).points.array.tobytes()
    back = read_las(tmp_path / "out.las")
    assert np.array_equal(back.attrs["classification"], cls)
    assert np.array_equal(back.attrs["treeID"], tree)
    assert np.all(back.attrs["synthetic"] == 1)
    assert np.array_equal(back.xyz, changed.xyz)
    # everything else untouched, bit for bit
    for name in ("intensity", "gps_time", "red", "user_data", "normal", "scaled", "withheld"):
        assert same(back.attrs[name], cloud.attrs[name]), name
    # an existing extra dimension keeps its type
    assert back.template.header.point_format.dimension_by_name("treeID").dtype == np.int32


def test_template_header_for_new_points(tmp_path):
    """A cloud whose points are not the template's records (here: two chunks merged)
    is written with the template's header (format, scales, VLRs, CRS) and its own
    coordinates and attributes."""
    src = tmp_path / "src.laz"
    make_las(src, "1.3", 3, n=1000)
    a, b = read_las_chunks(src, chunk_size=600)
    merged = PointCloud(np.concatenate([b.xyz, a.xyz]),
                        {k: np.concatenate([b.attrs[k], a.attrs[k]]) for k in a.attrs},
                        crs=a.crs, units=a.units, template=a.template)
    write_las(tmp_path / "merged.laz", merged)
    raw = laspy.read(str(src)).points.array
    out = laspy.read(str(tmp_path / "merged.laz"))
    assert out.points.array.tobytes() == np.concatenate([raw[600:], raw[:600]]).tobytes()
    assert vlr_keys(out.header.vlrs, False) == vlr_keys(laspy.read(str(src)).header.vlrs, False)


def test_values_that_do_not_fit_are_refused(tmp_path):
    src = tmp_path / "src.las"
    make_las(src, "1.2", 3, extra=False)
    cloud = read_las(src)
    bad = cloud.with_attrs(intensity=np.full(len(cloud), 70_000))
    with pytest.raises(InputError, match=r"out\.las.*intensity"):
        write_las(tmp_path / "out.las", bad)
    frac = cloud.with_attrs(classification=np.full(len(cloud), 2.5))
    with pytest.raises(InputError, match="classification"):
        write_las(tmp_path / "out.las", frac)
    assert not (tmp_path / "out.las").exists()


def test_standard_attribute_upgrades_the_point_format(tmp_path):
    src = tmp_path / "src.las"
    make_las(src, "1.2", 1, extra=False)
    cloud = read_las(src)
    red = (np.arange(len(cloud)) % 65536).astype(np.uint16)
    write_las(tmp_path / "rgb.las", cloud.with_attrs(red=red))
    back = read_las(tmp_path / "rgb.las")
    assert back.template.header.point_format.id == 3  # format 1 + RGB
    assert np.array_equal(back.attrs["red"], red)
    assert same(back.attrs["gps_time"], cloud.attrs["gps_time"])
    assert back.crs == UTM12


def test_write_without_template(tmp_path):
    rng = np.random.default_rng(3)
    xyz = rng.uniform([500000, 4000000, 100], [500100, 4000100, 140], (1000, 3))
    attrs = {"intensity": rng.integers(0, 4000, 1000).astype(np.uint16),
             "classification": rng.integers(1, 6, 1000).astype(np.uint8),
             "red": rng.integers(0, 65535, 1000).astype(np.uint16),
             "green": rng.integers(0, 65535, 1000).astype(np.uint16),
             "blue": rng.integers(0, 65535, 1000).astype(np.uint16),
             "ground": rng.random(1000) < 0.5}
    crs = pyproj.CRS.from_epsg(32633)
    cloud = PointCloud(xyz, attrs, crs=crs, units=units_of(crs))
    write_las(tmp_path / "new.laz", cloud, extra={"treeID": np.arange(1000, dtype=np.int32)})
    info = las_info(tmp_path / "new.laz")
    assert (info.version, info.point_format, info.point_count) == ("1.4", 7, 1000)
    hdr = laspy.open(str(tmp_path / "new.laz")).header
    assert np.allclose(hdr.scales, 0.001) and np.array_equal(hdr.offsets, np.floor(xyz.min(0)))
    assert hdr.vlrs.get("WktCoordinateSystemVlr") and hdr.global_encoding.wkt
    back = read_las(tmp_path / "new.laz")
    assert back.crs == crs
    # exact at the file's scale: what laspy's own quantisation gives
    assert np.array_equal(back.xyz, np.round((xyz - hdr.offsets) / 0.001) * 0.001 + hdr.offsets)
    assert np.abs(back.xyz - xyz).max() <= 0.0005 + 1e-9
    for name in ("intensity", "classification", "red", "green", "blue"):
        assert np.array_equal(back.attrs[name], attrs[name])
    assert np.array_equal(back.attrs["ground"], attrs["ground"].astype(np.uint8))
    assert np.array_equal(back.attrs["treeID"], np.arange(1000))
    # rewriting the read-back cloud is lossless
    write_las(tmp_path / "again.laz", back)
    assert_same_file(tmp_path / "new.laz", tmp_path / "again.laz")


def test_chunked_read_equals_full_read(tmp_path):
    src = tmp_path / "src.laz"
    make_las(src, "1.3", 5, n=2500)
    full = read_las(src)
    chunks = list(read_las_chunks(src, chunk_size=1000))
    assert [len(c) for c in chunks] == [1000, 1000, 500]
    assert np.array_equal(np.concatenate([c.xyz for c in chunks]), full.xyz)
    for name, values in full.attrs.items():
        got = np.concatenate([c.attrs[name] for c in chunks])
        assert same(got, values), name
    assert all(c.crs == full.crs and c.units == full.units for c in chunks)
    # a chunk writes back losslessly too
    write_las(tmp_path / "chunk.las", chunks[1])
    assert_same_file(src, tmp_path / "chunk.las", index=slice(1000, 2000))
    # progress is reported and cancelling stops the stream
    seen = []
    list(read_las_chunks(src, 1000, progress=lambda f, m: seen.append(f)))
    assert seen[-1] == 1.0
    from sylva.core.errors import Cancelled

    with pytest.raises(Cancelled):
        list(read_las_chunks(src, 1000, cancelled=lambda: True))


def test_crs_override(tmp_path):
    src = tmp_path / "src.las"
    make_las(src, "1.2", 0)
    cloud = read_las(src, crs="EPSG:2994")
    assert cloud.crs == pyproj.CRS.from_epsg(2994)
    assert cloud.units == Units(INTERNATIONAL_FOOT, INTERNATIONAL_FOOT)
    assert las_info(src, crs=2264).units.horizontal_m == US_SURVEY_FOOT
    # the override is what gets written
    write_las(tmp_path / "out.las", cloud)
    assert read_las(tmp_path / "out.las").crs == pyproj.CRS.from_epsg(2994)
    with pytest.raises(CRSError, match=r"src\.las.*not understood"):
        read_las(src, crs="EPSG:999999")
    # units can be overridden too (a tile without CRS known to be in US feet)
    assert read_cloud(src, units=US_SURVEY_FOOT).units == Units(US_SURVEY_FOOT, US_SURVEY_FOOT)
    assert read_las(src).units.is_metric


@pytest.mark.parametrize("crs,h,v", [
    ("EPSG:2994", INTERNATIONAL_FOOT, INTERNATIONAL_FOOT),  # Oregon Lambert, intl feet
    ("EPSG:2264", US_SURVEY_FOOT, US_SURVEY_FOOT),  # North Carolina, US survey feet
    ("EPSG:26910", METRE, METRE),  # UTM 10N
    ("EPSG:2994+5703", INTERNATIONAL_FOOT, METRE),  # feet + NAVD88 height in metres
    ("EPSG:26910+6360", METRE, US_SURVEY_FOOT),  # metres + NAVD88 height in US feet
])
@pytest.mark.parametrize("fmt", [1, 6])
def test_units_from_crs_in_file(tmp_path, crs, h, v, fmt):
    crs = pyproj.CRS(crs)
    assert units_of(crs) == Units(h, v)
    src = tmp_path / "src.laz"
    make_las(src, "1.4", fmt, n=50, crs=None, extra=False)
    cloud = read_las(src, crs=crs)  # write the CRS through our writer
    write_las(tmp_path / "out.laz", cloud)
    back = read_las(tmp_path / "out.laz")
    assert back.crs == crs
    assert back.units == Units(h, v)
    info = las_info(tmp_path / "out.laz")
    assert info.units == Units(h, v) and info.crs == crs
    assert back.units.is_metric == (h == v == METRE)


def test_geographic_crs_is_refused_when_reading(tmp_path):
    wgs84 = pyproj.CRS.from_epsg(4326)
    u = units_of(wgs84)
    assert np.isnan(u.horizontal_m) and u.vertical_m == METRE
    assert units_of(pyproj.CRS.from_epsg(4979)).vertical_m == METRE  # ellipsoidal height
    src = tmp_path / "lonlat.laz"
    make_las(src, "1.4", 6, n=10, crs=wgs84)
    assert np.isnan(las_info(src).units.horizontal_m)  # reported, not refused
    with pytest.raises(CRSError, match=r"lonlat\.laz: its CRS \(WGS 84\) is geographic"):
        read_las(src)
    assert read_las(src, crs=26912).crs == UTM12  # an override fixes a wrong record
    (tmp_path / "a.xyz").write_text("1 2 3\n")
    with pytest.raises(CRSError, match=r"a\.xyz: .* is geographic"):
        read_xyz(tmp_path / "a.xyz", crs=4326)


def test_geotiff_vertical_keys(tmp_path):
    """GeoTIFF keys: a vertical CRS key makes a compound CRS; unit keys give units."""
    src = tmp_path / "src.las"
    make_las(src, "1.2", 1, n=20, crs=pyproj.CRS.from_epsg(2994), extra=False)
    las = laspy.read(str(src))
    gk = las.header.vlrs.get("GeoKeyDirectoryVlr")[0]
    key = laspy.vlrs.known.GeoKeyEntryStruct()
    key.id, key.tiff_tag_location, key.count, key.value_offset = 4096, 0, 1, 5703
    gk.geo_keys.append(key)
    gk.geo_keys_header.number_of_keys += 1
    las.write(str(tmp_path / "vert.las"))
    cloud = read_las(tmp_path / "vert.las")
    assert cloud.crs.is_compound and cloud.crs.sub_crs_list[1] == pyproj.CRS.from_epsg(5703)
    assert cloud.units == Units(INTERNATIONAL_FOOT, METRE)
    key.id, key.value_offset = 4099, 9003  # only VerticalUnitsGeoKey: US survey feet
    las.write(str(tmp_path / "vunits.las"))
    cloud = read_las(tmp_path / "vunits.las")
    assert cloud.crs == pyproj.CRS.from_epsg(2994)
    assert cloud.units == Units(INTERNATIONAL_FOOT, US_SURVEY_FOOT)


def test_header_only_info(tmp_path):
    src = tmp_path / "src.laz"
    las = make_las(src, "1.3", 3)
    info = las_info(src)
    assert info.point_count == 3000 and info.point_format == 3 and info.version == "1.3"
    assert np.allclose(info.bounds, (*las.xyz.min(0), *las.xyz.max(0)))
    assert info.crs == UTM12 and info.units.is_metric and info.compressed
    assert info.file_size == src.stat().st_size and info.has_classification
    assert info.extra_dimensions == ("treeID", "height", "flag8", "scaled", "normal")


# ------------------------------------------------------------------ COPC


def test_copc_named_laz_reads_and_writes_as_plain_laz(tmp_path):
    """A .copc.laz-named LAZ 1.4 carrying COPC records (laspy cannot write COPC)
    reads as LAS; writing it back drops the COPC records, which would be stale."""
    src = tmp_path / "tile.copc.laz"
    las = make_las(src, "1.4", 6, extra=False, evlr=False)
    las.header.vlrs.insert(0, laspy.VLR("copc", 1, "copc info", bytes(160)))
    las.evlrs = laspy.vlrs.vlrlist.VLRList([laspy.VLR("copc", 1000, "EPT hierarchy", bytes(32))])
    las.write(str(src))
    cloud = read_cloud(src)
    assert len(cloud) == 3000 and cloud.crs == UTM12
    assert np.array_equal(cloud.xyz, las.xyz)
    write_las(tmp_path / "out.laz", cloud)
    out = laspy.read(str(tmp_path / "out.laz"))
    assert not [v for v in out.header.vlrs if v.user_id == "copc"]
    assert not [v for v in (out.evlrs or []) if v.user_id == "copc"]
    assert out.points.array.tobytes() == las.points.array.tobytes()


def test_real_copc_file(tmp_path):
    """A genuine COPC file (written by copc-lib: root node + one child node, so two
    variable-size LAZ chunks, hierarchy EVLR, WKT in an EVLR) reads as LAS."""
    copc = pytest.importorskip("copclib")
    rng = np.random.default_rng(11)
    n = 800
    fmt = laspy.PointFormat(7)
    arr = np.zeros(n, fmt.dtype())
    arr["X"], arr["Y"] = rng.integers(0, 10_000, n), rng.integers(0, 10_000, n)
    arr["Z"] = rng.integers(0, 3_000, n)
    arr["intensity"] = rng.integers(0, 1000, n)
    arr["classification"] = rng.integers(1, 6, n)
    arr["bit_fields"] = 0x11
    arr["red"], arr["gps_time"] = rng.integers(0, 65535, n), np.sort(rng.uniform(0, 9, n))
    offset = np.array([481000.0, 3812000.0, 0.0])
    xyz = np.column_stack([arr["X"], arr["Y"], arr["Z"]]) * 0.01 + offset
    lo, hi = xyz.min(0), xyz.max(0)
    centre, half = (lo + hi) / 2, float((hi - lo).max() / 2) + 1.0
    cfg = copc.CopcConfigWriter(7, copc.Vector3(0.01, 0.01, 0.01), copc.Vector3(*offset),
                                UTM12.to_wkt())
    cfg.las_header.min, cfg.las_header.max = copc.Vector3(*lo), copc.Vector3(*hi)
    info = cfg.copc_info
    info.center_x, info.center_y, info.center_z = map(float, centre)
    info.halfsize, info.spacing = half, 1.0
    child = np.all(xyz < centre, axis=1)  # the octant of voxel (1, 0, 0, 0)
    src = tmp_path / "tile.copc.laz"
    writer = copc.FileWriter(str(src), cfg)
    for key, sel in ((copc.VoxelKey.RootKey(), ~child), (copc.VoxelKey(1, 0, 0, 0), child)):
        writer.AddNode(key, copc.VectorChar(np.frombuffer(arr[sel].tobytes(), np.int8)))
    writer.Close()
    # it is real COPC: laspy's COPC reader queries it
    with laspy.CopcReader.open(str(src)) as reader:
        assert len(reader.query()) == n
    cloud = read_cloud(src)
    assert len(cloud) == n and cloud.crs == UTM12 and cloud.units.is_metric
    assert las_info(src).point_count == n and las_info(src).crs == UTM12
    expected = np.concatenate([arr[~child], arr[child]])  # file order: node by node
    assert cloud.template.array.tobytes() == expected.tobytes()
    assert np.array_equal(cloud.attrs["red"], expected["red"])
    chunks = list(read_las_chunks(src, chunk_size=300))
    assert np.array_equal(np.concatenate([c.xyz for c in chunks]), cloud.xyz)
    # written back as plain LAZ: no COPC records, same points, CRS kept
    write_las(tmp_path / "out.laz", cloud)
    out = laspy.read(str(tmp_path / "out.laz"))
    assert not [v for v in [*out.header.vlrs, *(out.evlrs or [])] if v.user_id == "copc"]
    assert out.points.array.tobytes() == expected.tobytes()
    assert out.header.parse_crs() == UTM12


# ------------------------------------------------------------------ text


def test_read_xyz_variants(tmp_path):
    rng = np.random.default_rng(5)
    xyz = np.round(rng.uniform(0, 100, (200, 3)), 3)
    inten = rng.integers(0, 1000, 200)
    rgb = rng.integers(0, 255, (200, 3))
    lines = [f"{a:.3f} {b:.3f} {c:.3f}" for a, b, c in xyz]

    (tmp_path / "a.xyz").write_text("\n".join(lines) + "\n")
    c = read_xyz(tmp_path / "a.xyz")
    assert np.array_equal(c.xyz, xyz) and c.attrs == {} and c.crs is None and c.units.is_metric

    body = "\n".join(f"{a:.3f},{b:.3f},{c_:.3f},{i},{r},{g},{b_}" for (a, b, c_), i, (r, g, b_)
                     in zip(xyz, inten, rgb))
    (tmp_path / "b.csv").write_text("# exported\nX,Y,Z,Intensity,R,G,B\n" + body + "\n")
    c = read_cloud(tmp_path / "b.csv", crs="EPSG:2994")
    assert np.array_equal(c.xyz, xyz) and c.crs == pyproj.CRS.from_epsg(2994)
    assert c.units.horizontal_m == INTERNATIONAL_FOOT
    assert c.attrs["intensity"].dtype == np.uint16 and np.array_equal(c.attrs["intensity"], inten)
    assert np.array_equal(np.column_stack([c.attrs[k] for k in ("red", "green", "blue")]), rgb)

    semi = "\n".join(f"{a:.3f};{b:.3f};{c_:.3f}".replace(".", ",") for a, b, c_ in xyz)
    (tmp_path / "c.txt").write_text("x;y;z\n" + semi + "\n\n")
    assert np.array_equal(read_xyz(tmp_path / "c.txt").xyz, xyz)

    pts = "\n".join(f"{a:.3f} {b:.3f} {c_:.3f} {i} {r} {g} {b_}  # pt" for (a, b, c_), i, (r, g, b_)
                    in zip(xyz, inten, rgb))
    (tmp_path / "d.pts").write_text("200\n" + pts)
    c = read_cloud(tmp_path / "d.pts", units=US_SURVEY_FOOT)
    assert np.array_equal(c.xyz, xyz) and c.units.vertical_m == US_SURVEY_FOOT
    assert list(c.attrs) == ["intensity", "red", "green", "blue"]

    (tmp_path / "e.txt").write_text("# x y z classification height\n" + "\n".join(
        f"{a} {b} {c_} 2 {c_ / 3}" for a, b, c_ in xyz))
    c = read_xyz(tmp_path / "e.txt")
    assert c.attrs["classification"].dtype == np.uint8
    assert np.allclose(c.attrs["height"], xyz[:, 2] / 3)

    # a comment block longer than the first 64 KiB scanned, latin-1 text in it
    long_comments = "".join(f"# métadonnées {i:06d} {'x' * 60}\n" for i in range(1200))
    (tmp_path / "f.xyz").write_bytes((long_comments + "\n".join(lines)).encode("latin-1"))
    assert np.array_equal(read_xyz(tmp_path / "f.xyz").xyz, xyz)
    # mixed separators ("x y,z") are read through the cleaned-text path
    mixed = "\n".join(f"{a:.3f} {b:.3f},{c_:.3f}" for a, b, c_ in xyz)
    (tmp_path / "g.txt").write_text(mixed)
    assert np.array_equal(read_xyz(tmp_path / "g.txt").xyz, xyz)

    # a text cloud writes to LAS (no template) and reads back
    write_las(tmp_path / "e.las", c)
    back = read_las(tmp_path / "e.las")
    assert np.abs(back.xyz - xyz).max() < 1e-9 and np.all(back.attrs["classification"] == 2)


def test_read_xyz_bad_input(tmp_path):
    (tmp_path / "ragged.xyz").write_text("1 2 3\n4 5 6\n7 8\n9 10 11\n")
    with pytest.raises(InputError, match=r"ragged\.xyz: line 3"):
        read_xyz(tmp_path / "ragged.xyz")
    (tmp_path / "words.xyz").write_text("1 2 3\n4 five 6\n")
    with pytest.raises(InputError, match=r"words\.xyz: line 2"):
        read_xyz(tmp_path / "words.xyz")
    (tmp_path / "empty.xyz").write_text("# nothing\nx y z\n")
    with pytest.raises(EmptyInputError, match=r"empty\.xyz.*no points"):
        read_xyz(tmp_path / "empty.xyz")
    assert len(read_xyz(tmp_path / "empty.xyz", allow_empty=True)) == 0
    (tmp_path / "two.xyz").write_text("1 2\n3 4\n")
    with pytest.raises(InputError, match=r"two\.xyz.*at least 3"):
        read_xyz(tmp_path / "two.xyz")
    with pytest.raises(InputError, match=r"nothere\.xyz: file not found"):
        read_xyz(tmp_path / "nothere.xyz")
    with pytest.raises(InputError, match=r"cloud\.e57.*unknown point-cloud type"):
        read_cloud(tmp_path / "cloud.e57")


# ------------------------------------------------------------------ bad input


def test_bad_las_inputs_name_the_file(tmp_path):
    missing = tmp_path / "missing.laz"
    for call in (read_las, las_info, lambda p: read_las_chunks(p)):
        with pytest.raises(InputError, match=r"missing\.laz: file not found"):
            call(missing)

    text = tmp_path / "text.las"
    text.write_text("1 2 3\n4 5 6\n" * 100)
    with pytest.raises(InputError, match=r"text\.las: not a readable LAS/LAZ file"):
        read_las(text)

    src = tmp_path / "full.laz"
    make_las(src, "1.4", 6, n=20000)
    half = tmp_path / "half.laz"
    half.write_bytes(src.read_bytes()[: src.stat().st_size // 2])
    with pytest.raises(InputError, match=r"half\.laz: the file is truncated"):
        read_las(half)
    with pytest.raises(InputError, match=r"half\.laz: the file is truncated"):
        for _ in read_las_chunks(half, 5000):
            pass

    with pytest.raises(InputError, match=r"half\.laz: the file is truncated"):
        las_info(half)  # the LAZ chunk table is missing: known from the header alone

    las_src = tmp_path / "full.las"
    make_las(las_src, "1.2", 1, n=2000)
    cut = tmp_path / "cut.las"
    cut.write_bytes(las_src.read_bytes()[:-100])
    with pytest.raises(InputError, match=r"cut\.las: the file is truncated"):
        read_las(cut)

    for name in ("empty.las", "empty.laz"):
        empty = tmp_path / name
        make_las(empty, "1.4", 6, n=0)
        with pytest.raises(EmptyInputError, match=name + ": the file holds no points"):
            read_las(empty)
        with pytest.raises(EmptyInputError, match=name):
            read_las_chunks(empty)
        assert len(read_las(empty, allow_empty=True)) == 0
        assert las_info(empty).point_count == 0

    garbled = tmp_path / "garbled.las"
    make_las(garbled, "1.4", 6, n=10, crs=None)
    las = laspy.read(str(garbled))
    las.header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr("PROJCS[not a crs"))
    las.write(str(garbled))
    with pytest.raises(CRSError, match=r"garbled\.las: its CRS record cannot be understood"):
        read_las(garbled)
    assert read_las(garbled, crs="EPSG:2994").units.horizontal_m == INTERNATIONAL_FOOT

    nocrs = tmp_path / "nocrs.laz"
    make_las(nocrs, "1.2", 3, n=10, crs=None)
    cloud = read_las(nocrs)
    assert cloud.crs is None and cloud.units.is_metric
    with pytest.raises(CRSError, match=r"nocrs\.laz has no CRS; pass one with the CRS parameter"):
        require_crs(cloud)
    assert require_crs(read_las(nocrs, crs=26912)) is not None

    # every one of these is a SylvaError, never a bare library exception
    assert issubclass(CRSError, SylvaError) and issubclass(EmptyInputError, SylvaError)


def test_failed_write_leaves_nothing_behind(tmp_path):
    src = tmp_path / "src.las"
    make_las(src, "1.4", 6, n=100)
    cloud = read_las(src)
    out = tmp_path / "out.laz"
    with pytest.raises(InputError, match=r"out\.laz: extra dimension 'treeID' has 3 values"):
        write_las(out, cloud, extra={"treeID": np.zeros(3, np.int32)})
    far = PointCloud(cloud.xyz + [1e9, 0, 0], cloud.attrs, crs=cloud.crs, template=cloud.template)
    with pytest.raises(InputError, match=r"out\.laz: x coordinates .* do not fit"):
        write_las(out, far)
    with pytest.raises(InputError, match="does not exist"):
        write_las(tmp_path / "no" / "out.las", cloud)
    # a failure while the bytes are being written (cancel after encoding) removes the temp
    calls = iter([False, False, True])  # checked on entry, before and after writing
    from sylva.core.errors import Cancelled

    with pytest.raises(Cancelled):
        write_las(out, cloud, cancelled=lambda: next(calls))
    # an existing file is only replaced by a complete one
    write_las(out, cloud)
    before = out.read_bytes()
    with pytest.raises(InputError):
        write_las(out, cloud, extra={"x y": np.zeros(2)})
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.laz", "src.las"]


# ------------------------------------------------------------------ the shared real files


def _shared(name):
    path = DATA / name
    if not path.exists():
        pytest.skip(f"{path} is not available")
    return path


def test_real_mixed_conifer():
    path = _shared("MixedConifer.laz")
    cloud = read_las(path)
    assert len(cloud) == 37657
    assert cloud.crs.to_epsg() == 26912 and cloud.units == Units(METRE, METRE)
    assert "treeID" in cloud.attrs and set(np.unique(cloud.attrs["classification"])) >= {2}
    las = laspy.read(str(path))
    assert np.array_equal(cloud.xyz, las.xyz)
    assert np.array_equal(cloud.attrs["treeID"], np.asarray(las["treeID"]))
    info = las_info(path)
    assert info.point_count == 37657 and info.crs.to_epsg() == 26912


def test_real_autzen(tmp_path):
    path = _shared("autzen_trim.laz")
    cloud = read_las(path)
    assert len(cloud) == 110000
    assert cloud.crs.is_projected and "Lambert" in cloud.crs.to_wkt()
    assert cloud.units == Units(INTERNATIONAL_FOOT, INTERNATIONAL_FOOT)
    assert {"red", "green", "blue"} <= set(cloud.attrs)
    # local metres: an Oregon tile ~ hundreds of metres across, not thousands of feet
    span = np.ptp(cloud.local_xyz(), axis=0)
    assert np.allclose(span, np.ptp(cloud.xyz, axis=0) * 0.3048)
    write_las(tmp_path / "autzen.laz", cloud, extra={"treeID": np.zeros(len(cloud), np.int32)})
    back = read_las(tmp_path / "autzen.laz")
    assert back.crs == cloud.crs and np.array_equal(back.xyz, cloud.xyz)
    assert np.array_equal(back.attrs["red"], cloud.attrs["red"])
    # without its WKT records, autzen's GeoTIFF keys describe a user-defined Lambert
    # projection pyproj cannot build: no CRS, but the linear-units key still says feet
    las = laspy.read(str(path))
    for v in [v for v in las.header.vlrs if v.record_id == 2112]:
        las.header.vlrs.remove(v)
    las.write(str(tmp_path / "keys_only.laz"))
    keys_only = read_las(tmp_path / "keys_only.laz")
    assert keys_only.crs is None
    assert keys_only.units == Units(INTERNATIONAL_FOOT, INTERNATIONAL_FOOT)


def test_real_ahn3_text():
    path = _shared("ahn3_delft.xyz")
    cloud = read_cloud(path)
    assert len(cloud) == 2488 and cloud.crs is None and cloud.units.is_metric
    ref = np.loadtxt(path)
    assert np.array_equal(cloud.xyz, ref[:, :3])
    with pytest.raises(CRSError, match="ahn3_delft.xyz has no CRS"):
        require_crs(cloud)
    assert read_cloud(path, crs="EPSG:28992").crs.to_epsg() == 28992


def test_a_lazrs_panic_at_the_end_of_the_data_is_the_end():
    """lazrs 0.6 (laspy 2.5's backend, Debian 13's) panics past the last chunk instead of raising: a pyo3
    PanicException, a BaseException; it means the same end of the data, while Ctrl-C still propagates."""
    from types import SimpleNamespace

    from sylva.core.io.las import check_no_more_points

    class PanicException(BaseException):
        pass

    def reader(exc):
        def decompress_many(buf):
            raise exc
        return SimpleNamespace(point_source=SimpleNamespace(decompressor=SimpleNamespace(
            decompress_many=decompress_many)))

    header = SimpleNamespace(are_points_compressed=True, point_format=SimpleNamespace(size=30), point_count=5)
    check_no_more_points(reader(PanicException("slice index starts at 3 but ends at 2")), "x.laz", header)
    check_no_more_points(reader(RuntimeError("end")), "x.laz", header)
    with pytest.raises(KeyboardInterrupt):
        check_no_more_points(reader(KeyboardInterrupt()), "x.laz", header)
