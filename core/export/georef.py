"""Frames every 3D writer shares: source CRS <-> geodetic <-> ECEF <-> local east-north-up.

The chain for a model vertex ``v`` (metres, tree-local grid frame, see
:mod:`sylva.core.export.model`)::

    source = base + v / (h_unit, h_unit, v_unit)            CRS units
    (lon, lat, h) = PROJ(source CRS, 3D) -> WGS 84 (EPSG:4979)   degrees, ellipsoidal metres
    ECEF = PROJ(EPSG:4979 -> EPSG:4978)                     metres, WGS 84 geocentric
    ENU = R(lon0, lat0)^T (ECEF - ECEF0)                    metres at the origin

with the usual rotation (columns east, north, up of the origin)::

    R = [[-sin l, -sin p cos l, cos p cos l],
         [ cos l, -sin p sin l, cos p sin l],
         [     0,        cos p,      sin p]]

3D Tiles wants WGS 84 ECEF, so the geodetic step always ends on WGS 84 (for
ETRS89/NAD83 sources PROJ applies its best available datum transformation).

**Vertical.**  A 2D CRS (e.g. EPSG:32632) says nothing about heights: z is
then treated as an ellipsoidal height (documented in every file's metadata
as ``"vertical": "ellipsoidal (assumed)"``).  A compound CRS with a geoid
based vertical CRS (e.g. EPSG:32632+5783) is converted to ellipsoidal heights
by PROJ when the geoid grid is installed; otherwise a :class:`UserWarning` is
issued and heights are treated as ellipsoidal ("ellipsoidal (assumed; geoid
grid unavailable)").  For a tree model only *relative* heights inside one
tile matter in a viewer; an undulation error shifts the whole tile up or down.

**Per-tree affine map.**  The map local -> ENU is smooth; across one tree
(tens of metres) its second-order term is below 0.1 mm (earth curvature
d^2 / 2R = 0.08 mm at 30 m), so each tree's base is transformed exactly and
its vertices with the Jacobian at the base (central differences, 1 m steps):
``ENU(v) = ENU(base) + J v``.  J holds the meridian convergence and the
projection's scale factor.

**Local engineering CRS / no CRS.**  Without a geodetic datum there is no
ECEF: :meth:`Georef.require_geodetic` raises :class:`CRSError` (3D Tiles),
while glTF, OBJ and CityGML still work in the grid frame (ENU := grid axes,
metres, relative to the origin).

GeographicLib supplies what pyproj has no call for: :func:`geodesic_distance`
(Karney's geodesic on WGS 84), used to cross-check horizontal ENU distances.
"""
from __future__ import annotations

import math
import threading
import warnings
from typing import Optional

import numpy as np

from ..errors import CRSError
from .model import ExportFrame

__all__ = ["Georef", "enu_to_ecef_matrix", "geodesic_distance", "Z_UP_TO_Y_UP", "Y_UP_TO_Z_UP"]

#: glTF is y-up.  This column-major-compatible 4x4 maps z-up ENU (E, N, U) to
#: glTF (x, y, z) = (E, U, -N): a -90 degree rotation about x.
Z_UP_TO_Y_UP = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, -1.0, 0, 0], [0, 0, 0, 1.0]])
#: Its inverse, which 3D Tiles clients apply to glTF content ("glTF transforms", +90 deg about x).
Y_UP_TO_Z_UP = Z_UP_TO_Y_UP.T.copy()


_LOCAL = threading.local()
_MEMO_SIZE = 32


def _memo(key, make):
    """``make()``, memoised per thread under ``key`` (at most ``_MEMO_SIZE`` entries).

    Every tile's exports build the same few pyproj objects (a transformer takes ~5 ms); pyproj
    objects are not shared between threads.  Sylva, not in the paper.
    """
    memo = getattr(_LOCAL, "memo", None)
    if memo is None:
        memo = _LOCAL.memo = {}
    if key not in memo:
        if len(memo) >= _MEMO_SIZE:
            memo.clear()
        memo[key] = make()
    return memo[key]


def _epsg(code: int):
    """``pyproj.CRS.from_epsg(code)`` (memoised, :func:`_memo`)."""
    from pyproj import CRS

    return _memo(("epsg", code), lambda: CRS.from_epsg(code))


def _transformer(src, dst):
    """``pyproj.Transformer.from_crs(src, dst, always_xy=True)``, memoised (:func:`_memo`) by the CRSs' WKT."""
    from pyproj import Transformer

    key = ("transformer", src.to_wkt(), dst.to_wkt())
    if key[1] is None or key[2] is None:
        return Transformer.from_crs(src, dst, always_xy=True)
    return _memo(key, lambda: Transformer.from_crs(src, dst, always_xy=True))


def enu_rotation(lon_deg: float, lat_deg: float) -> np.ndarray:
    """3x3 matrix whose columns are the east, north, up unit vectors in ECEF."""
    lam, phi = math.radians(lon_deg), math.radians(lat_deg)
    sl, cl, sp, cp = math.sin(lam), math.cos(lam), math.sin(phi), math.cos(phi)
    return np.array([[-sl, -sp * cl, cp * cl],
                     [cl, -sp * sl, cp * sl],
                     [0.0, cp, sp]])


def enu_to_ecef_matrix(lon_deg: float, lat_deg: float, ecef_origin) -> np.ndarray:
    """4x4 (row-major numpy) transform from ENU at the origin to ECEF; ``.T.ravel()`` gives glTF/3D Tiles order."""
    m = np.eye(4)
    m[:3, :3] = enu_rotation(lon_deg, lat_deg)
    m[:3, 3] = np.asarray(ecef_origin, dtype=np.float64)
    return m


def geodesic_distance(lon1, lat1, lon2, lat2) -> float:
    """Geodesic distance in metres on WGS 84 (GeographicLib, Karney 2013)."""
    from geographiclib.geodesic import Geodesic

    return float(Geodesic.WGS84.Inverse(lat1, lon1, lat2, lon2)["s12"])


class Georef:
    """Conversions between a source CRS, WGS 84 geodetic, ECEF and ENU at ``origin``.

    ``frame`` an :class:`ExportFrame`; ``origin`` (3,) in source CRS
    coordinates (e.g. the tile centre at ground level).  All methods take and
    return (n, 3) float64 arrays.
    """

    def __init__(self, frame: ExportFrame, origin):
        self.frame = frame
        self.crs = frame.pyproj_crs()
        self.units = frame.resolved_units()
        self.scale = np.array([self.units.horizontal_m] * 2 + [self.units.vertical_m])
        self.origin = np.asarray(origin, dtype=np.float64).reshape(3)
        self.vertical = "none (local frame)"
        self._fwd = None
        self._in_scale = np.ones(3)
        if self.crs is not None and self.crs.geodetic_crs is not None:
            self._set_up_geodetic()
        if self.has_geodetic:
            llh = self.source_to_geodetic(self.origin[None])[0]
            self.origin_llh = llh
            self.origin_ecef = self.geodetic_to_ecef(llh[None])[0]
            self.rotation = enu_rotation(llh[0], llh[1])
        else:
            self.origin_llh = None
            self.origin_ecef = None
            self.rotation = np.eye(3)

    # ------------------------------------------------------------------ set-up
    def _set_up_geodetic(self):
        from pyproj.transformer import TransformerGroup

        crs = self.crs
        if crs.is_bound:
            crs = crs.source_crs
        if crs.is_geographic and not crs.is_projected and len(crs.axis_info) < 3 \
                and math.isnan(self.units.horizontal_m):
            raise CRSError(f"{crs.name}: geographic CRS; tree bases must be in a projected CRS")
        wgs84 = _epsg(4979)
        src3d = None
        if crs.is_compound:
            horizontal = next((s for s in crs.sub_crs_list if not s.is_vertical), None)
            vertical = next((s for s in crs.sub_crs_list if s.is_vertical), None)
            if horizontal is None:
                raise CRSError(f"{crs.name}: compound CRS without a horizontal part")
            try:
                group = TransformerGroup(crs, wgs84, always_xy=True)
                usable = group.best_available and len(group.transformers) > 0
            except Exception:  # PROJ could not even list operations
                usable, group = False, None
            if usable:
                tr = group.transformers[0]
                vfac = vertical.axis_info[0].unit_conversion_factor
                hfac = horizontal.axis_info[0].unit_conversion_factor
                z_in = self.origin[2] * self.units.vertical_m / vfac
                _, _, h = tr.transform(self.origin[0] * self.units.horizontal_m / hfac,
                                       self.origin[1] * self.units.horizontal_m / hfac, z_in)
                # a "ballpark" vertical operation passes heights through unchanged
                if math.isfinite(h) and abs(h - z_in * vfac) > 1e-6:
                    src3d = crs
                    self.vertical = f"ellipsoidal (converted from {vertical.name} by PROJ)"
            if src3d is None:
                warnings.warn(f"{crs.name}: no geoid grid is installed for {vertical.name}; "
                              f"heights are treated as ellipsoidal heights (a constant offset "
                              f"of the whole tile in viewers)", UserWarning, stacklevel=3)
                src3d = horizontal.to_3d()
                self.vertical = "ellipsoidal (assumed; geoid grid unavailable)"
        elif len(crs.axis_info) >= 3:
            src3d = crs
            self.vertical = "ellipsoidal (the CRS is 3D)"
        else:
            wkt = crs.to_wkt()
            src3d = crs.to_3d() if wkt is None else _memo(("to_3d", wkt), crs.to_3d)
            self.vertical = "ellipsoidal (assumed; the CRS has no vertical component)"
        axes = src3d.axis_info
        h_fac = axes[0].unit_conversion_factor
        v_fac = axes[2].unit_conversion_factor if len(axes) >= 3 else 1.0
        if crs.is_compound and src3d is crs:
            vert = next(s for s in crs.sub_crs_list if s.is_vertical)
            v_fac = vert.axis_info[0].unit_conversion_factor
        # source units -> the units PROJ expects for src3d
        self._in_scale = np.array([self.units.horizontal_m / h_fac] * 2 + [self.units.vertical_m / v_fac])
        self._src3d, self._wgs84, self._ecef = src3d, wgs84, _epsg(4978)
        self._fwd = _transformer(src3d, wgs84)
        self._to_ecef = _transformer(wgs84, self._ecef)

    # ------------------------------------------------------------------ properties
    @property
    def has_geodetic(self) -> bool:
        """True when the CRS has a geodetic datum (ECEF and 3D Tiles are possible)."""
        return self._fwd is not None

    def require_geodetic(self, what: str) -> None:
        if not self.has_geodetic:
            name = "no CRS" if self.crs is None else f"the CRS {self.crs.name!r}"
            raise CRSError(f"{what}: {name} has no geodetic datum (a local engineering frame), "
                           f"so the trees cannot be placed on the globe (ECEF); assign the real "
                           f"CRS of the point cloud, or export glTF/OBJ in the local frame")

    @property
    def enu_to_ecef(self) -> np.ndarray:
        """4x4 ENU(origin) -> ECEF (row-major numpy)."""
        self.require_geodetic("ENU to ECEF")
        return enu_to_ecef_matrix(self.origin_llh[0], self.origin_llh[1], self.origin_ecef)

    def describe(self) -> dict:
        """The georeferencing block written into every file (JSON-serialisable)."""
        d = {"frame": "ENU" if self.has_geodetic else "local grid",
             "axes": "x east, y north, z up (metres); glTF nodes are y-up below a root matrix",
             "crs_name": self.crs.name if self.crs is not None else None,
             "crs_epsg": self.epsg,
             "crs_wkt": self.crs.to_wkt() if self.crs is not None else None,
             "units": {"horizontal_m": self.units.horizontal_m, "vertical_m": self.units.vertical_m},
             "vertical": self.vertical,
             "origin_source": [float(c) for c in self.origin]}
        if self.has_geodetic:
            d["origin_lon_lat_h"] = [float(c) for c in self.origin_llh]
            d["origin_ecef"] = [float(c) for c in self.origin_ecef]
            d["enu_to_ecef"] = [float(c) for c in self.enu_to_ecef.T.ravel()]
        return d

    @property
    def epsg(self) -> Optional[int]:
        if self.crs is None:
            return None
        try:
            return self.crs.to_epsg(min_confidence=100)
        except Exception:
            return None

    # ------------------------------------------------------------------ conversions
    def source_to_geodetic(self, src) -> np.ndarray:
        """Source CRS coordinates (its units) -> (lon, lat, h) WGS 84, degrees and ellipsoidal metres."""
        self.require_geodetic("geodetic coordinates")
        p = np.asarray(src, dtype=np.float64).reshape(-1, 3) * self._in_scale
        lon, lat, h = self._fwd.transform(p[:, 0], p[:, 1], p[:, 2])
        out = np.column_stack([lon, lat, h])
        if not np.all(np.isfinite(out)):
            raise CRSError(f"{self.crs.name}: PROJ could not transform some coordinates "
                           f"(outside the CRS's area?), e.g. {np.asarray(src).reshape(-1, 3)[0].tolist()}")
        return out

    def geodetic_to_source(self, llh) -> np.ndarray:
        self.require_geodetic("geodetic coordinates")
        q = np.asarray(llh, dtype=np.float64).reshape(-1, 3)
        x, y, z = _transformer(self._wgs84, self._src3d).transform(q[:, 0], q[:, 1], q[:, 2])
        return np.column_stack([x, y, z]) / self._in_scale

    def geodetic_to_ecef(self, llh) -> np.ndarray:
        q = np.asarray(llh, dtype=np.float64).reshape(-1, 3)
        x, y, z = self._to_ecef.transform(q[:, 0], q[:, 1], q[:, 2])
        return np.column_stack([x, y, z])

    def ecef_to_geodetic(self, ecef) -> np.ndarray:
        q = np.asarray(ecef, dtype=np.float64).reshape(-1, 3)
        lon, lat, h = _transformer(self._ecef, self._wgs84).transform(q[:, 0], q[:, 1], q[:, 2])
        return np.column_stack([lon, lat, h])

    def ecef_to_enu(self, ecef) -> np.ndarray:
        return (np.asarray(ecef, dtype=np.float64).reshape(-1, 3) - self.origin_ecef) @ self.rotation

    def enu_to_ecef_points(self, enu) -> np.ndarray:
        return np.asarray(enu, dtype=np.float64).reshape(-1, 3) @ self.rotation.T + self.origin_ecef

    def source_to_enu(self, src) -> np.ndarray:
        """Source CRS -> ENU at the origin (grid metres relative to the origin without a datum)."""
        src = np.asarray(src, dtype=np.float64).reshape(-1, 3)
        if not self.has_geodetic:
            return (src - self.origin) * self.scale
        return self.ecef_to_enu(self.geodetic_to_ecef(self.source_to_geodetic(src)))

    def enu_to_source(self, enu) -> np.ndarray:
        enu = np.asarray(enu, dtype=np.float64).reshape(-1, 3)
        if not self.has_geodetic:
            return enu / self.scale + self.origin
        return self.geodetic_to_source(self.ecef_to_geodetic(self.enu_to_ecef_points(enu)))

    def local_to_source(self, local_m, base) -> np.ndarray:
        """Tree-local metres -> source CRS coordinates: ``base + local / units``."""
        return np.asarray(base, dtype=np.float64) + np.asarray(local_m, dtype=np.float64).reshape(-1, 3) / self.scale

    def source_to_local(self, src, base) -> np.ndarray:
        return (np.asarray(src, dtype=np.float64).reshape(-1, 3) - np.asarray(base, dtype=np.float64)) * self.scale

    def tree_frames(self, bases, step_m: float = 1.0):
        """(ENU of each base (n, 3), Jacobians (n, 3, 3)) with ``ENU(v) ~= ENU(base) + J @ v``.

        One vectorised PROJ call for all bases and their +-``step_m`` neighbours
        along each local axis (central differences).
        """
        bases = np.asarray(bases, dtype=np.float64).reshape(-1, 3)
        n = len(bases)
        if not self.has_geodetic:
            return (bases - self.origin) * self.scale, np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
        offs = np.concatenate([np.zeros((1, 3)), np.eye(3) * step_m, -np.eye(3) * step_m])  # (7, 3)
        pts = bases[:, None, :] + offs[None] / self.scale                                   # (n, 7, 3)
        enu = self.source_to_enu(pts.reshape(-1, 3)).reshape(n, 7, 3)
        jac = (enu[:, 1:4] - enu[:, 4:7]) / (2.0 * step_m)  # (n, axis, 3): d ENU / d local_axis
        return enu[:, 0], np.transpose(jac, (0, 2, 1))

    def model_to_enu(self, local_m, base) -> np.ndarray:
        """Exact (per-vertex PROJ) tree-local metres -> ENU; for checks (writers use :meth:`tree_frames`)."""
        return self.source_to_enu(self.local_to_source(local_m, base))


def default_origin(models) -> np.ndarray:
    """Origin of a file: the centre of the bases' bounding box at the lowest ground z (source CRS)."""
    b = np.array([m.base for m in models], dtype=np.float64)
    lo, hi = b.min(axis=0), b.max(axis=0)
    return np.array([(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, lo[2]])


def prj_text(crs) -> str:
    """The ``.prj`` text of a CRS: ESRI WKT1 when PROJ can write it, else WKT2."""
    if crs is None:
        return ""
    for version in ("WKT1_ESRI", "WKT2_2019"):
        try:
            text = crs.to_wkt(version)
        except Exception:
            text = None
        if text:
            return text
    return crs.to_wkt()


def write_sidecars(path, georef: Georef, extra: Optional[dict] = None):
    """``<path>.prj`` (when there is a CRS) and ``<path>.origin.json`` (the georeferencing block)."""
    import json
    from pathlib import Path

    from .model import atomic_write_bytes

    path = Path(path)
    stem = path.with_suffix("")
    out = []
    if georef.crs is not None:
        out.append(atomic_write_bytes(stem.with_name(stem.name + ".prj"), prj_text(georef.crs).encode()))
    block = georef.describe()
    if extra:
        block.update(extra)
    out.append(atomic_write_bytes(stem.with_name(stem.name + ".origin.json"),
                                  (json.dumps(block, indent=1, sort_keys=True) + "\n").encode()))
    return out
