"""Batched polylines: Hermite smoothing, rotation-minimising frames and generalised cylinders.

Cubic Hermite curves through a chain's points (Hu et al. 2017 §5.5, :func:`hermite_smooth`), rotation-minimising
frames by the double reflection method of Wang, Jüttler, Zheng & Liu 2008 (:func:`rotation_minimizing_frames`)
and tubes swept along them (Yan et al. 2009 §4.2, :func:`sweep_tube`).  The batch forms (:func:`dedupe`,
:func:`hermite_batch`, :func:`tube_batch`) work on many polylines at once, given as points with offsets;
:func:`norm3` is the row norm they (and the forest passes elsewhere) share.
"""
from __future__ import annotations

from typing import Optional, Tuple

import numpy as np

from ..errors import InputError


_EPS = 1e-9


def _seg_ids(offsets: np.ndarray) -> np.ndarray:
    """Polyline id of every point of a batch given offsets (n_lines + 1,)."""
    return np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))


def dedupe(points, radii, offsets, eps=_EPS):
    """Drop points equal to the previous point of the same polyline."""
    n = len(points)
    keep = np.ones(n, dtype=bool)
    if n > 1:
        same = np.ones(n, dtype=bool)
        same[offsets[:-1]] = False  # first point of each line is never a duplicate
        d = norm3(np.diff(points, axis=0))
        keep[1:] = ~(same[1:] & (d <= eps))
    lid = _seg_ids(offsets)[keep]
    counts = np.bincount(lid, minlength=len(offsets) - 1)
    return points[keep], radii[keep], np.r_[0, np.cumsum(counts)], keep


def _tangents(points: np.ndarray, offsets: np.ndarray, unit: bool = True) -> np.ndarray:
    """Finite-difference tangents per polyline (central inside, one-sided at the ends)."""
    n = len(points)
    t = np.zeros_like(points)
    if n == 0:
        return t
    first = np.zeros(n, dtype=bool)
    last = np.zeros(n, dtype=bool)
    first[offsets[:-1][np.diff(offsets) > 0]] = True
    last[offsets[1:][np.diff(offsets) > 0] - 1] = True
    nxt = np.minimum(np.arange(n) + 1, n - 1)
    prv = np.maximum(np.arange(n) - 1, 0)
    nxt = np.where(last, np.arange(n), nxt)
    prv = np.where(first, np.arange(n), prv)
    t = points[nxt] - points[prv]
    if unit:
        norm = norm3(t)[:, None]
        t = t / np.where(norm > 0, norm, 1.0)
    return t


def hermite_batch(points, radii, offsets, samples):
    """Cubic Hermite (Catmull-Rom tangents, chord-length scaled) through each polyline.

    Returns sampled points, radii and new offsets: a line of k points becomes
    (k - 1) * samples + 1 points through the original ones.
    """
    samples = int(samples)
    if samples <= 1 or len(points) == 0:
        return points, radii, offsets
    n = len(points)
    lid = _seg_ids(offsets)
    k = np.diff(offsets)
    seg_ok = np.zeros(n, dtype=bool)
    seg_ok[:-1] = lid[:-1] == lid[1:]
    s0 = np.flatnonzero(seg_ok)               # segment s0 -> s0 + 1
    d = norm3(points[s0 + 1] - points[s0])
    # derivative w.r.t. arc length at every point: (p_{i+1} - p_{i-1}) / (d_{i-1} + d_i)
    dlen = np.zeros(n)       # length of the segment leaving each point
    dlen[s0] = d
    prev_len = np.zeros(n)
    prev_len[s0 + 1] = d
    first = np.zeros(n, dtype=bool)
    first[offsets[:-1][k > 0]] = True
    last = np.zeros(n, dtype=bool)
    last[offsets[1:][k > 0] - 1] = True
    i = np.arange(n)
    nxt = np.where(last, i, np.minimum(i + 1, n - 1))
    prv = np.where(first, i, np.maximum(i - 1, 0))
    denom = np.where(last, 0, dlen) + np.where(first, 0, prev_len)
    deriv = (points[nxt] - points[prv]) / np.where(denom > 0, denom, 1.0)[:, None]
    t = np.arange(samples) / samples
    t2, t3 = t * t, t * t * t
    h00 = 2 * t3 - 3 * t2 + 1
    h10 = t3 - 2 * t2 + t
    h01 = -2 * t3 + 3 * t2
    h11 = t3 - t2
    p0, p1 = points[s0], points[s0 + 1]
    m0 = deriv[s0] * d[:, None]
    m1 = deriv[s0 + 1] * d[:, None]
    h00, h10, h01, h11, t = (h[:, None] for h in (h00, h10, h01, h11, t))
    seg_pts = np.empty((samples, len(s0), 3))   # sample-major: long inner loops
    for c in range(3):
        seg_pts[:, :, c] = h00 * p0[:, c] + h10 * m0[:, c] + h01 * p1[:, c] + h11 * m1[:, c]
    seg_rad = radii[s0] + t * (radii[s0 + 1] - radii[s0])
    new_k = np.where(k > 0, (k - 1) * samples + 1, 0)
    new_off = np.r_[0, np.cumsum(new_k)]
    out_p = np.empty((new_off[-1], 3))
    out_r = np.empty(new_off[-1])
    local = s0 - offsets[lid[s0]]
    pos = (new_off[lid[s0]] + local * samples + np.arange(samples)[:, None]).ravel()
    out_p[pos] = seg_pts.reshape(-1, 3)
    out_r[pos] = seg_rad.ravel()
    ends = np.flatnonzero(k > 0)
    out_p[new_off[ends + 1] - 1] = points[offsets[ends + 1] - 1]
    out_r[new_off[ends + 1] - 1] = radii[offsets[ends + 1] - 1]
    return out_p, out_r, new_off


def hermite_smooth(points: np.ndarray, samples_per_segment: int = 4,
                   radii: Optional[np.ndarray] = None):
    """Cubic Hermite curve through a chain of points, Hu et al. 2017 §5.5.

    Each segment ``p_i -> p_{i+1}`` becomes ``samples_per_segment`` points of
    the cubic Hermite curve with Catmull-Rom tangents taken in chord-length
    parametrisation (``m_i = (p_{i+1} - p_{i-1}) / (d_{i-1} + d_i)``, scaled by
    the segment length; one-sided at the ends), which equals the uniform
    Catmull-Rom spline for evenly spaced points and does not overshoot at
    uneven ones.  The curve passes through every input point; the output has
    ``(k - 1) * samples_per_segment + 1`` points.  With ``radii`` (k,) returns
    ``(points, radii)`` with radii interpolated linearly along each segment.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if samples_per_segment < 1:
        raise InputError(f"samples_per_segment must be >= 1, got {samples_per_segment}")
    r = np.zeros(len(pts)) if radii is None else np.asarray(radii, dtype=np.float64).reshape(-1)
    if len(r) != len(pts):
        raise InputError(f"{len(r)} radii for {len(pts)} centre-line points")
    sp, sr, _ = hermite_batch(pts, r, np.array([0, len(pts)]), samples_per_segment)
    return sp if radii is None else (sp, sr)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products of (n, 3) arrays (column arithmetic: faster than np.cross here)."""
    a = np.broadcast_to(a, np.broadcast_shapes(np.shape(a), np.shape(b)))
    b = np.broadcast_to(b, a.shape)
    out = np.empty(a.shape)
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def norm3(v: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(v, axis=-1)`` of (..., 3) vectors, the same bits (sqrt((x² + y²) + z²)), without
    numpy's slow reduction over a length-3 axis."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return np.sqrt((x * x + y * y) + z * z)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products of (n, 3) arrays."""
    return np.einsum("ij,ij->i", a, b)


def _initial_normal(t: np.ndarray) -> np.ndarray:
    """A unit normal per tangent: horizontal (z x t) where possible, else x."""
    ref = np.zeros_like(t)
    ref[:, 2] = 1.0
    steep = np.abs(t[:, 2]) > 0.999
    r = _cross(ref, t)
    r[steep] = _cross(np.array([0.0, 1.0, 0.0]), t[steep])
    return r / np.maximum(norm3(r)[:, None], 1e-300)


def _qrotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors (n, 3) by unit quaternions (n, 4)."""
    w, u = q[:, :1], q[:, 1:]
    uv = _cross(u, v)
    return v + 2.0 * w * uv + 2.0 * _cross(u, uv)


def _rmf_batch(points, tangents, offsets, normal0=None):
    """Rotation-minimising frames for a batch of polylines (Wang et al. 2008, double reflection).

    Each step maps ``r_i`` to ``r_{i+1} = H2 H1 r_i``, with H1 the reflection
    in the bisector plane of ``x_i x_{i+1}`` (normal ``v1 = x_{i+1} - x_i``)
    and H2 the reflection with normal ``v2 = t_{i+1} - H1 t_i``.  Both depend
    only on the points and tangents, and a product of two reflections with
    unit normals ``a`` then ``b`` is the rotation by the quaternion ``b a``.
    So the frames are the segmented prefix products of these quaternions
    applied to each line's first normal: a Hillis-Steele scan of log2(k)
    vectorised quaternion products over all lines at once.  Returns (r, s)
    unit normals with (t, r, s) a right-handed orthonormal frame per point.
    """
    n = len(points)
    if n == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    lid = _seg_ids(offsets)
    start = offsets[:-1][lid]
    quat = np.zeros((n, 4))
    quat[:, 0] = 1.0                                  # quat[i] maps frame i-1 -> frame i
    inner = np.flatnonzero(np.arange(n) > start)
    if len(inner):
        v1 = points[inner] - points[inner - 1]
        c1 = _dot(v1, v1)
        ok1 = c1 > 1e-30
        a = v1 / np.sqrt(np.where(ok1, c1, 1.0))[:, None]
        t_prev = tangents[inner - 1]
        t_l = t_prev - 2.0 * _dot(a, t_prev)[:, None] * a
        v2 = tangents[inner] - t_l
        c2 = _dot(v2, v2)
        ok2 = c2 > 1e-30
        b = v2 / np.sqrt(np.where(ok2, c2, 1.0))[:, None]
        q = np.empty((len(inner), 4))
        q[:, 0] = -_dot(a, b)                # b a = (-b.a, b x a)
        q[:, 1:] = _cross(b, a)
        q[~(ok1 & ok2)] = (1.0, 0.0, 0.0, 0.0)        # degenerate step: keep the frame
        quat[inner] = q
    # segmented inclusive scan: P[i] = q[i] q[i-1] ... q[start]
    w, x, y, z = (np.ascontiguousarray(quat[:, c]) for c in range(4))
    idx = np.arange(n)
    off = 1
    while True:
        valid = np.flatnonzero(idx - off >= start)
        if len(valid) == 0:
            break
        src = valid - off
        aw, ax, ay, az = w[valid], x[valid], y[valid], z[valid]
        bw, bx, by, bz = w[src], x[src], y[src], z[src]
        w[valid] = aw * bw - ax * bx - ay * by - az * bz
        x[valid] = aw * bx + ax * bw + ay * bz - az * by
        y[valid] = aw * by - ax * bz + ay * bw + az * bx
        z[valid] = aw * bz + ax * by - ay * bx + az * bw
        off *= 2
    norm = np.sqrt(w * w + x * x + y * y + z * z)
    quat = np.stack([w / norm, x / norm, y / norm, z / norm], axis=1)
    first = offsets[:-1][np.diff(offsets) > 0]
    r0 = np.zeros((len(offsets) - 1, 3))
    if normal0 is None:
        r0[np.diff(offsets) > 0] = _initial_normal(tangents[first])
    else:
        r0[:] = np.asarray(normal0, dtype=np.float64).reshape(-1, 3)
    r = _qrotate(quat, r0[lid])
    r -= _dot(r, tangents)[:, None] * tangents
    norm = norm3(r)[:, None]
    bad = norm[:, 0] < 1e-12
    if bad.any():
        r[bad] = _initial_normal(tangents[bad])
        norm[bad] = 1.0
    r /= norm
    s = _cross(tangents, r)
    return r, s


def rotation_minimizing_frames(points: np.ndarray, tangents: Optional[np.ndarray] = None,
                               normal0: Optional[np.ndarray] = None) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotation-minimising frames along a polyline by the double reflection method.

    Wang, Jüttler, Zheng & Liu 2008, "Computation of rotation minimizing
    frames", ACM TOG 27(1), Algorithm "double reflection" (as Yan et al. 2009
    §4.2 use for lofting): ``r_{i+1} = H2 H1 r_i`` with H1 the reflection in
    the bisector plane of ``x_i x_{i+1}`` and H2 the reflection that then maps
    the reflected tangent onto ``t_{i+1}``.  ``tangents`` default to
    finite-difference tangents; ``normal0`` (3,) is the first normal
    (default: horizontal).  Returns ``(t, r, s)``, each (k, 3), with ``s = t x r``.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    off = np.array([0, len(pts)])
    if tangents is None:
        t = _tangents(pts, off)
    else:
        t = np.asarray(tangents, dtype=np.float64).reshape(-1, 3)
        t = t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-300)
    if normal0 is not None and len(pts):
        n0 = np.asarray(normal0, dtype=np.float64).reshape(3)
        n0 = n0 - (n0 @ t[0]) * t[0]
        if np.linalg.norm(n0) < 1e-12:
            raise InputError("normal0 must not be parallel to the first tangent")
        normal0 = n0 / np.linalg.norm(n0)
    r, s = _rmf_batch(pts, t, off, normal0)
    return t, r, s


def tube_batch(points, radii, offsets, sides, cap=True, normal0=None):
    """Vertices and faces of one closed (or open) tube per polyline of the batch.

    Returns (vertices, faces, face_line): ring vertices of all lines, then the
    cap centres; faces wound outwards; ``face_line`` the polyline per face.
    """
    sides = int(sides)
    if sides < 3:
        raise InputError(f"a tube needs at least 3 sides, got {sides}")
    n = len(points)
    nl = len(offsets) - 1
    if n == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.int64)
    t = _tangents(points, offsets)
    r, s = _rmf_batch(points, t, offsets, normal0)
    ang = 2.0 * np.pi * np.arange(sides) / sides
    ca, sa = np.cos(ang)[:, None], np.sin(ang)[:, None]
    # vertex j * n + i is corner j of ring i (side-major, so every array
    # operation below runs over the long axis)
    k = np.diff(offsets)
    lines = np.flatnonzero(k >= 2) if cap else np.zeros(0, dtype=np.int64)
    nb = len(lines)
    verts = np.empty((n * sides + 2 * nb, 3))
    for c in range(3):
        verts[:n * sides, c] = (points[:, c] + radii * (ca * r[:, c] + sa * s[:, c])).ravel()
    lid = _seg_ids(offsets)
    # side quads between ring i and i + 1 of the same line, two triangles each
    pair = np.flatnonzero(lid[:-1] == lid[1:]) if n > 1 else np.zeros(0, dtype=np.int64)
    j = np.arange(sides)[:, None]
    a = (j * n + pair).ravel()
    b = (((j + 1) % sides) * n + pair).ravel()
    q = len(a)
    quads = np.empty((2 * q, 3), dtype=np.int64)
    quads[:q, 0], quads[:q, 1], quads[:q, 2] = a, b, b + 1
    quads[q:, 0], quads[q:, 1], quads[q:, 2] = a, b + 1, a + 1
    faces = [quads]
    fl = np.tile(lid[pair], sides)
    face_line = [fl, fl]
    if nb:
        first = offsets[lines]
        last = offsets[lines + 1] - 1
        base = n * sides
        verts[base:base + nb] = points[first]
        verts[base + nb:] = points[last]
        cf = np.broadcast_to(base + np.arange(nb), (sides, nb)).ravel()
        cl = cf + nb
        caps = np.empty((2 * sides * nb, 3), dtype=np.int64)
        h = sides * nb
        caps[:h, 0], caps[:h, 1], caps[:h, 2] = cf, (((j + 1) % sides) * n + first).ravel(), (j * n + first).ravel()
        caps[h:, 0], caps[h:, 1], caps[h:, 2] = cl, (j * n + last).ravel(), (((j + 1) % sides) * n + last).ravel()
        faces.append(caps)
        cfl = np.tile(lines, sides)
        face_line += [cfl, cfl]
    faces = np.concatenate(faces)
    face_line = np.concatenate(face_line).astype(np.int64)
    return verts, faces, face_line


def sweep_tube(centreline: np.ndarray, radii, sides: int = 8, cap: bool = True,
               normal0: Optional[np.ndarray] = None) -> Tuple[np.ndarray, np.ndarray]:
    """A generalised cylinder (Hu et al. 2017 §5.5, Yan et al. 2009 §4.2) along any centre line.

    A regular ``sides``-gon of radius ``radii[i]`` is placed in the normal
    plane at every centre-line point, oriented by rotation-minimising frames
    (double reflection, Wang et al. 2008) so the tube never twists or flips;
    consecutive rings are joined by two triangles per side, and with ``cap``
    both ends are closed by triangle fans, making the tube watertight with
    outward normals.  ``radii`` is a scalar or (k,) metres.  Consecutive
    duplicate points are dropped.  Returns ``(vertices (v, 3), faces (f, 3))``.
    """
    pts = np.asarray(centreline, dtype=np.float64).reshape(-1, 3)
    r = np.broadcast_to(np.asarray(radii, dtype=np.float64), (len(pts),)).astype(np.float64)
    if not np.all(np.isfinite(pts)) or not np.all(np.isfinite(r)) or (r < 0).any():
        raise InputError("centre line and radii must be finite and radii >= 0 m")
    pts, r, off, _ = dedupe(pts, r, np.array([0, len(pts)]))
    if len(pts) < 2:
        raise InputError("a tube needs a centre line of at least two distinct points")
    n0 = None
    if normal0 is not None:
        _, rr, _ = rotation_minimizing_frames(pts[:2], normal0=normal0)
        n0 = rr[0]
    v, f, _ = tube_batch(pts, r, off, sides, cap, n0)
    return v, f
