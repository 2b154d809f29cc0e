"""CityGML 2.0 (and 3.0) SolitaryVegetationObjects of tree models (lxml).

One ``core:CityModel`` with a ``gml:boundedBy`` envelope and one
``veg:SolitaryVegetationObject gml:id="tree_<id>"`` per tree holding, in the
order of the vegetation schema:

* ``gml:name`` ``tree <id>``; generic attributes for every attribute
  (2.0: ``gen:intAttribute`` / ``gen:doubleAttribute`` / ``gen:stringAttribute``;
  3.0: ``core:genericAttribute`` wrapping ``gen:IntAttribute`` ...);
* ``veg:class`` (the ``class`` attribute, else ``"tree"``), ``veg:species``
  when known, ``veg:height``, ``veg:trunkDiameter`` (dbh) and
  ``veg:crownDiameter`` in metres (``uom="m"``);
* geometry by level of detail, triangles as ``gml:MultiSurface`` of
  ``gml:Polygon`` in SOURCE CRS coordinates (``srsName`` on the envelope
  and on each MultiSurface, ``srsDimension="3"``).  2.0: ``lod1Geometry``
  the coarsest ``TreeModel.lods`` wood (when present), ``lod2Geometry`` the
  full wood (plus the leaf cards with ``leaves=True``).  3.0 (which has no
  LOD1 multi-surface for spaces): ``lod2MultiSurface`` the full model;
* or, with ``implicit=True``, ``lod2ImplicitRepresentation``: models that
  share one wood mesh object share one prototype ``gml:MultiSurface`` (in
  tree-local metres) written once and referenced by ``xlink:href``, each
  with its ``transformationMatrix`` (4x4 row-major: metres to CRS units)
  and ``referencePoint`` (the base).

In 3.0 (GML 3.2) every GML object needs a ``gml:id``: polygons are
``<tree>_<lod>_<k>``.  ``srsName`` is ``EPSG:<code>`` when PROJ identifies
one, else the CRS name (a WKT-only CRS has no URN; its WKT is in the
``.prj`` written alongside).  Files validate against the official XSDs shipped
in citygml4j's jars (Maven Central ``org.citygml4j:citygml4j:2.12.0`` for
2.0, ``org.citygml4j:citygml4j-xml:3.0.0`` for 3.0), see tests/test_viewers.py.
"""
from __future__ import annotations

from pathlib import Path
from typing import Dict, List, Sequence

import numpy as np

from ..errors import InputError
from ..progress import check, report
from .georef import Georef, default_origin, write_sidecars
from .model import ExportFrame, TreeModel, atomic_open, check_models

__all__ = ["write_citygml", "NS", "NS3", "srs_name"]

NS = {
    "core": "http://www.opengis.net/citygml/2.0",
    "veg": "http://www.opengis.net/citygml/vegetation/2.0",
    "gen": "http://www.opengis.net/citygml/generics/2.0",
    "gml": "http://www.opengis.net/gml",
    "xlink": "http://www.w3.org/1999/xlink",
    "xsi": "http://www.w3.org/2001/XMLSchema-instance",
}
#: CityGML 3.0 namespaces (GML 3.2).
NS3 = {
    "core": "http://www.opengis.net/citygml/3.0",
    "veg": "http://www.opengis.net/citygml/vegetation/3.0",
    "gen": "http://www.opengis.net/citygml/generics/3.0",
    "gml": "http://www.opengis.net/gml/3.2",
    "xlink": "http://www.w3.org/1999/xlink",
    "xsi": "http://www.w3.org/2001/XMLSchema-instance",
}
_SCHEMA_LOCATION = {
    "2.0": ("http://www.opengis.net/citygml/vegetation/2.0 "
            "http://schemas.opengis.net/citygml/vegetation/2.0/vegetation.xsd "
            "http://www.opengis.net/citygml/generics/2.0 "
            "http://schemas.opengis.net/citygml/generics/2.0/generics.xsd"),
    "3.0": ("http://www.opengis.net/citygml/vegetation/3.0 "
            "https://schemas.opengis.net/citygml/vegetation/3.0/vegetation.xsd "
            "http://www.opengis.net/citygml/generics/3.0 "
            "https://schemas.opengis.net/citygml/generics/3.0/generics.xsd"),
}


class _Dialect:
    """Tag names and namespaces of one CityGML version."""

    def __init__(self, version: str):
        if version not in ("2.0", "3.0"):
            raise InputError(f"CityGML export: version must be '2.0' or '3.0', got {version!r}")
        self.version = version
        self.v3 = version == "3.0"
        self.ns = NS3 if self.v3 else NS

    def q(self, prefix: str, tag: str) -> str:
        return f"{{{self.ns[prefix]}}}{tag}"


def srs_name(georef: Georef) -> str:
    """``EPSG:<code>``; for a compound CRS of two EPSG CRSs the OGC compound URN
    ``urn:ogc:def:crs,crs:EPSG::<horizontal>,crs:EPSG::<vertical>`` (the form German
    and Dutch CityGML files use); else the CRS name (its WKT is in the .prj)."""
    if georef.crs is None:
        return "local"
    code = georef.epsg
    if code is not None:
        return f"EPSG:{code}"
    if georef.crs.is_compound:
        codes = [sub.to_epsg(min_confidence=100) for sub in georef.crs.sub_crs_list]
        if all(c is not None for c in codes):
            return "urn:ogc:def:crs," + ",".join(f"crs:EPSG::{c}" for c in codes)
    return georef.crs.name


def _pos_lists(vertices: np.ndarray, faces: np.ndarray, fmt: str) -> List[str]:
    """One closed-ring posList string (4 positions) per triangle."""
    rings = vertices[np.concatenate([faces, faces[:, :1]], axis=1)].reshape(len(faces), 12)
    return [fmt % tuple(r) for r in rings.tolist()]


_MEMBER = ("<gml:surfaceMember><gml:Polygon{}><gml:exterior><gml:LinearRing><gml:posList>{}"
           "</gml:posList></gml:LinearRing></gml:exterior></gml:Polygon></gml:surfaceMember>")


def _multisurface(d: _Dialect, parent, vertices, faces, fmt, srs, gml_id, deferred: list):
    """A gml:MultiSurface ``gml_id`` of one Polygon per triangle, appended to ``parent``.

    lxml builds the MultiSurface element; its many small polygon members are
    formatted as text in one pass and stored in ``deferred``, and the element
    holds a marker that :func:`write_citygml` replaces by that text after
    lxml has serialised the tree (building ~5 elements per triangle in lxml
    and serialising them was 80% of the run time).
    """
    from lxml import etree

    ms = etree.SubElement(parent, d.q("gml", "MultiSurface"))
    if gml_id:
        ms.set(d.q("gml", "id"), gml_id)
    if srs is not None:
        ms.set("srsName", srs)
        ms.set("srsDimension", "3")
    pos = _pos_lists(vertices, faces, fmt)
    ids = [f' gml:id="{gml_id}_{k}"' for k in range(len(pos))] if d.v3 else [""] * len(pos)
    ms.text = _marker(len(deferred))
    deferred.append("\n" + "\n".join(_MEMBER.format(i, p) for i, p in zip(ids, pos)) + "\n")
    return ms


def _marker(k: int) -> str:
    return f"@@sylva-geometry-{k}@@"


def _generic(d: _Dialect, parent, key: str, value):
    from lxml import etree

    if value is None:
        return
    if isinstance(value, bool):
        kind, text = "string", "true" if value else "false"
    elif isinstance(value, int):
        kind, text = "int", str(value)
    elif isinstance(value, float):
        kind, text = "double", repr(value)
    else:
        kind, text = "string", str(value)
    if d.v3:
        el = etree.SubElement(etree.SubElement(parent, d.q("core", "genericAttribute")),
                              d.q("gen", kind.capitalize() + "Attribute"))
        etree.SubElement(el, d.q("gen", "name")).text = str(key)
    else:
        el = etree.SubElement(parent, d.q("gen", kind + "Attribute"), name=str(key))
    etree.SubElement(el, d.q("gen", "value")).text = text


def _length(d: _Dialect, parent, tag, value):
    from lxml import etree

    if value is None:
        return
    try:
        v = float(value)
    except (TypeError, ValueError):
        return
    if np.isfinite(v):
        etree.SubElement(parent, d.q("veg", tag), uom="m").text = repr(v)


def _geometry(m: TreeModel, leaves: bool):
    wv, wf = m.wood_arrays()
    parts_v, parts_f = [wv], [wf]
    if leaves:
        lv, lf, _ = m.leaf_arrays()
        parts_v.append(lv)
        parts_f.append(lf + len(wv))
    return np.concatenate(parts_v), np.concatenate(parts_f)


def _bounds(models, georef: Georef, leaves: bool):
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for m in models:
        v, f = _geometry(m, leaves)
        pts = [m.base[None]]
        if len(f):
            pts.append(georef.local_to_source(v[np.unique(f)], m.base))
        if m.lods:
            cv, cf = m.wood_arrays(min(m.lods))
            if len(cf):
                pts.append(georef.local_to_source(cv[np.unique(cf)], m.base))
        p = np.concatenate(pts)
        lo, hi = np.minimum(lo, p.min(axis=0)), np.maximum(hi, p.max(axis=0))
    return lo, hi


def _member(d: _Dialect, m: TreeModel, georef: Georef, srs: str, fmt: str, leaves: bool, implicit: bool,
            prototypes: Dict[tuple, str], deferred: list):
    """The core:cityObjectMember element of one tree."""
    from lxml import etree

    q = d.q
    member = etree.Element(q("core", "cityObjectMember"), nsmap=dict(d.ns))
    svo = etree.SubElement(member, q("veg", "SolitaryVegetationObject"))
    svo.set(q("gml", "id"), m.name)
    etree.SubElement(svo, q("gml", "name")).text = f"tree {m.tree_id}"
    attrs = m.json_attributes()
    for key, value in attrs.items():
        _generic(d, svo, key, value)

    def thematic():
        etree.SubElement(svo, q("veg", "class")).text = str(attrs.get("class") or "tree")
        if attrs.get("species"):
            etree.SubElement(svo, q("veg", "species")).text = str(attrs["species"])
        _length(d, svo, "height", attrs.get("height"))
        _length(d, svo, "trunkDiameter", attrs.get("dbh"))
        _length(d, svo, "crownDiameter", attrs.get("crown_diameter"))

    if not d.v3:        # 2.0: thematic attributes first, then geometry
        thematic()
    v_local, f_all = _geometry(m, leaves)
    if not implicit:
        if m.lods and not d.v3:
            cv, cf = m.wood_arrays(min(m.lods))
            if len(cf):
                _multisurface(d, etree.SubElement(svo, q("veg", "lod1Geometry")),
                              georef.local_to_source(cv, m.base), cf, fmt, srs, f"{m.name}_lod1", deferred)
        if len(f_all):
            prop = q("core", "lod2MultiSurface") if d.v3 else q("veg", "lod2Geometry")
            _multisurface(d, etree.SubElement(svo, prop), georef.local_to_source(v_local, m.base), f_all,
                          fmt, srs, f"{m.name}_lod2", deferred)
    else:
        prop = "core" if d.v3 else "veg"
        rep = etree.SubElement(svo, q(prop, "lod2ImplicitRepresentation"))
        ig = etree.SubElement(rep, q("core", "ImplicitGeometry"))
        if d.v3:
            ig.set(q("gml", "id"), f"{m.name}_implicit")
        mat = np.diag(np.r_[1.0 / georef.scale, 1.0])
        etree.SubElement(ig, q("core", "transformationMatrix")).text = " ".join(repr(float(x)) for x in mat.ravel())

        def relative():
            rel = etree.SubElement(ig, q("core", "relativeGeometry" if d.v3 else "relativeGMLGeometry"))
            key = (id(m.wood), id(m.leaves) if leaves else None)
            if key in prototypes:
                rel.set(q("xlink", "href"), "#" + prototypes[key])
            else:
                pid = f"prototype_{len(prototypes) + 1}"
                prototypes[key] = pid
                _multisurface(d, rel, v_local, f_all, fmt, None, pid, deferred)

        def reference():
            point = etree.SubElement(etree.SubElement(ig, q("core", "referencePoint")), q("gml", "Point"),
                                     srsName=srs, srsDimension="3")
            if d.v3:
                point.set(q("gml", "id"), f"{m.name}_reference")
            etree.SubElement(point, q("gml", "pos")).text = " ".join(repr(float(c)) for c in m.base)

        if d.v3:        # 3.0: referencePoint before relativeGeometry
            reference()
            relative()
        else:
            relative()
            reference()
    if d.v3:            # 3.0: geometry (AbstractSpace) first, then the vegetation attributes
        thematic()
    return member


def write_citygml(models: Sequence[TreeModel], path, frame: ExportFrame, leaves: bool = False,
                  implicit: bool = False, decimals: int = 3, version: str = "2.0", progress=None,
                  cancelled=None) -> List[Path]:
    """Write a CityGML 2.0 file of SolitaryVegetationObjects; returns the paths (file, .prj, .origin.json).

    ``leaves`` adds the leaf cards to lod2Geometry (large files); ``implicit``
    writes ImplicitGeometry reusing one prototype per distinct wood mesh;
    ``decimals`` of the coordinates in CRS units; ``version`` "2.0" or "3.0".
    """
    try:
        from lxml import etree
    except ImportError:
        raise InputError("CityGML export needs lxml: install python3-lxml (Debian) or `pip install lxml`")

    path = Path(path)
    d = _Dialect(version)
    q = d.q
    models = check_models(models, f"CityGML export to {path}")
    if not path.parent.exists():
        raise InputError(f"CityGML export: the output folder {path.parent} does not exist")
    georef = Georef(frame, default_origin(models))
    srs = srs_name(georef)
    fmt = " ".join([f"%.{int(decimals)}f"] * 12)
    lo, hi = _bounds(models, georef, leaves)
    prototypes: Dict[tuple, str] = {}
    # Streamed: the CityModel's head, each tree's member as lxml serialises it (without
    # the namespace declarations it repeats from the CityModel), then the tail.
    model = etree.Element(q("core", "CityModel"), {q("xsi", "schemaLocation"): _SCHEMA_LOCATION[version]},
                          nsmap=dict(d.ns))
    if d.v3:
        model.set(q("gml", "id"), "sylva_trees")
    etree.SubElement(model, q("gml", "name")).text = f"Sylva trees ({len(models)})"
    env = etree.SubElement(etree.SubElement(model, q("gml", "boundedBy")), q("gml", "Envelope"),
                           srsName=srs, srsDimension="3")
    etree.SubElement(env, q("gml", "lowerCorner")).text = " ".join(repr(float(c)) for c in lo)
    etree.SubElement(env, q("gml", "upperCorner")).text = " ".join(repr(float(c)) for c in hi)
    head = etree.tostring(model, encoding="UTF-8", xml_declaration=True, pretty_print=True)
    tail = b"</core:CityModel>\n"
    head = head[:head.rindex(tail)]
    decl = b"".join(b' xmlns:%s="%s"' % (k.encode(), v.encode()) for k, v in d.ns.items())
    with atomic_open(path) as fh:
        fh.write(head)
        for k, m in enumerate(models):
            check(cancelled)
            deferred: list = []
            member = etree.tostring(_member(d, m, georef, srs, fmt, leaves, implicit, prototypes, deferred),
                                    encoding="UTF-8", pretty_print=True)
            first = member.index(b">")
            member = member[:first].replace(decl, b"") + member[first:]
            for j, text in enumerate(deferred):
                member = member.replace(_marker(j).encode(), text.encode(), 1)
            fh.write(member)
            report(progress, 0.9 * (k + 1) / len(models), f"tree {m.tree_id}")
        fh.write(tail)
    written = [path]
    written.extend(write_sidecars(path, georef, {"frame": "source CRS",
                                                 "axes": "CRS coordinates as the CRS defines them"}))
    report(progress, 1.0, "done")
    return written
