"""Fingerprints of outputs for golden-file tests: integers and texts exactly, floats within a tolerance.

    fp = fingerprint(mesh.vertices, mesh.faces)        # {"exact": hash, "floats": [[sum, |sum|, weighted, nans]]}
    same_outputs({"mesh": fp}, golden) == []           # names whose fingerprints differ

A float array is summed three ways (plain, absolute, weighted by fixed random weights, so that a
reordering shows) and compared relative to its magnitude (:data:`RTOL`): the last bit of a float,
which differs from one CPU to another (numba compiles for the host), passes; a real change does not.
"""
from __future__ import annotations

import hashlib
import json
import struct

import numpy as np

from sylva.core.export.gltf import accessor_array, read_glb


def _floats(a) -> list:
    """A float array as [sum, sum of |x|, sum weighted by fixed random weights (a reordering shows), NaNs]."""
    a = np.asarray(a, dtype=np.float64).ravel()
    nan = np.isnan(a)
    a = np.where(nan, 0.0, a)
    w = np.random.default_rng(len(a)).uniform(0.5, 1.5, len(a))
    return [float(a.sum()), float(np.abs(a).sum()), float(a @ w), int(nan.sum())]


def fingerprint(*arrays) -> dict:
    """What outputs are made of: shapes, integers, booleans and texts exactly (a hash), floats by
    :func:`_floats`, which :func:`same_outputs` compares within a tolerance (the last bit of a float
    may differ from one CPU to another: numba compiles for the host)."""
    m, floats = hashlib.sha256(), []
    for a in arrays:
        if isinstance(a, dict):                      # an earlier fingerprint
            m.update(a["exact"].encode())
            floats.extend(a["floats"])
            continue
        a = np.asarray(a)
        m.update(str(a.shape).encode())
        if a.dtype.kind == "f":
            floats.append(_floats(a))
        elif a.dtype.kind == "O":
            m.update("|".join(str(x) for x in a.ravel()).encode())
        else:
            m.update(np.ascontiguousarray(a.astype(np.int64)).tobytes())
    return {"exact": m.hexdigest()[:16], "floats": floats}


def _json_parts(obj, floats: list):
    """``obj`` with its floats taken out (into ``floats``), for :func:`fingerprint`."""
    if isinstance(obj, float):
        floats.append(obj)
        return "f"
    if isinstance(obj, dict):
        return {k: _json_parts(v, floats) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_json_parts(v, floats) for v in obj]
    return obj


def json_fingerprint(doc) -> dict:
    floats = []
    structure = json.dumps(_json_parts(doc, floats), sort_keys=True)
    return fingerprint(np.array([structure], dtype=object), np.array(floats, dtype=np.float64))


#: Tolerance of the float sums, relative to the sum of |x| (+ 1): a last-bit difference passes, a
#: centimetre's move of one vertex among a million coordinates does not.
RTOL = 1e-9


def same_outputs(got: dict, want: dict) -> list:
    """Names of the outputs whose fingerprints differ (exactly, or floats beyond :data:`RTOL`)."""
    changed = []
    for name in sorted(set(got) | set(want)):
        a, b = got.get(name), want.get(name)
        ok = (a is not None and b is not None and a["exact"] == b["exact"] and len(a["floats"]) == len(b["floats"])
              and all(x[3] == y[3] and all(abs(u - v) <= RTOL * (y[1] + 1.0) or u == v for u, v in zip(x[:3], y[:3]))
                      for x, y in zip(a["floats"], b["floats"])))
        if not ok:
            changed.append(name)
    return changed


def glb_fingerprint(data: bytes) -> dict:
    """The content of a GLB: its JSON and every accessor (see :func:`fingerprint`), its images' bytes exactly."""
    doc, binary = read_glb(data)
    parts = [json_fingerprint(doc)]
    for k in range(len(doc.get("accessors", []))):
        parts.append(fingerprint(accessor_array(doc, binary, k)))
    for im in doc.get("images", []):
        v = doc["bufferViews"][im["bufferView"]]
        parts.append(fingerprint(np.frombuffer(binary[v["byteOffset"]:v["byteOffset"] + v["byteLength"]], dtype=np.uint8)))
    return fingerprint(*parts)


def wkb_fingerprint(blobs) -> dict:
    """Fingerprint of little-endian ISO WKB geometries (points, lines, polygons, triangles, multi-geometries,
    polyhedral surfaces, TINs; None for a missing geometry): their structure exactly, coordinates as floats."""
    ints, coords = [], []
    for blob in blobs:
        if blob is None:
            ints.append(-1)
            continue
        blob = bytes(blob)

        def geom(pos):
            order, kind = struct.unpack_from("<BI", blob, pos)
            ints.extend([order, kind])
            pos += 5
            dims = {0: 2, 1: 3, 2: 3, 3: 4}[kind // 1000]                 # ISO: +1000 Z, +2000 M
            base = kind % 1000
            if base == 1:                                              # a point
                coords.extend(struct.unpack_from(f"<{dims}d", blob, pos))
                return pos + 8 * dims
            (count,) = struct.unpack_from("<I", blob, pos)
            ints.append(count)
            pos += 4
            if base == 2:                                              # a linestring: its points
                coords.extend(struct.unpack_from(f"<{count * dims}d", blob, pos))
                return pos + 8 * count * dims
            if base in (3, 17):                                        # a polygon or triangle: its rings
                for _ in range(count):
                    (n,) = struct.unpack_from("<I", blob, pos)
                    ints.append(n)
                    coords.extend(struct.unpack_from(f"<{n * dims}d", blob, pos + 4))
                    pos += 4 + 8 * n * dims
                return pos
            for _ in range(count):                                     # multi-geometries, surfaces, TINs
                pos = geom(pos)
            return pos

        assert geom(0) == len(blob)
    return fingerprint(np.array(ints, dtype=np.int64), np.array(coords, dtype=np.float64))


def rows_fingerprint(rows) -> dict:
    """GeoPackage rows: texts and integers exactly, floats (values, envelopes, coordinates) as floats."""
    texts, floats = [], []
    for row in rows:
        for v in row:
            if isinstance(v, bytes) and v[:2] == b"GP":
                env = {0: 0, 1: 4, 2: 6, 3: 6, 4: 8}[(v[3] >> 1) & 7]
                floats.extend(np.frombuffer(v[8:8 + 8 * env], dtype="<f8").tolist())
                wkb = wkb_fingerprint([v[8 + 8 * env:]])
                texts.append(f"GP{v[2:4].hex()}{v[4:8].hex()}{wkb['exact']}")
                floats.extend(x for f in wkb["floats"] for x in f[:3])
            elif isinstance(v, float):
                texts.append("f")
                floats.append(v)
            else:
                texts.append(repr(v))
        texts.append("\n")
    return fingerprint(np.array(texts, dtype=object), np.array(floats, dtype=np.float64))
