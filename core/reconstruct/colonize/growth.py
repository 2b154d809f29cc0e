"""The compiled guided-growth loop: Guo et al. 2018 §5.2 (Eq. 6-9, L-system 1).

:func:`grow_kernel` runs the sequential space-colonisation iterations (buds, perception cones, marker
assignment, growth units, kill distance) on the growable node arrays :class:`Nodes`; :func:`roll_tables`
gives it the roll angles.  Compiling the loop with uniform grids in place of the per-iteration k-d trees is
Sylva's (see :mod:`sylva.core.reconstruct.colonize`).
"""
from __future__ import annotations

import numpy as np

from ...jit import helper, njit


_K_BUDS = 8          # nearest buds examined per marker for the perception test
_STALL_LIMIT = 6     # consecutive iterations without growth (d_i widened x1.5 each) before stopping


@helper
def grown_nodes(cap, m, pos, heading, parent, n_children, seed, bud_free, added, leader):
    """The node arrays of :func:`grow_kernel` (:class:`Nodes`'s) moved into arrays of ``cap`` rows, their
    first ``m`` rows kept, the new rows zero (``parent`` -1)."""
    p = np.zeros((cap, 3))
    p[:m] = pos[:m]
    h = np.zeros((cap, 3))
    h[:m] = heading[:m]
    a = np.full(cap, -1, dtype=np.int64)
    a[:m] = parent[:m]
    c = np.zeros(cap, dtype=np.int64)
    c[:m] = n_children[:m]
    s = np.zeros(cap, dtype=np.bool_)
    s[:m] = seed[:m]
    f = np.zeros(cap, dtype=np.bool_)
    f[:m] = bud_free[:m]
    d = np.zeros(cap, dtype=np.bool_)
    d[:m] = added[:m]
    e = np.zeros(cap, dtype=np.bool_)
    e[:m] = leader[:m]
    return p, h, a, c, s, f, d, e


@njit
def grow_kernel(markers, weight, active, pos, heading, parent, n_children, seed, bud_free, added,
                leader, m, stall, boost, it_lo, it_hi, di_of_t, cos_tab, sin_tab, l, dk,
                cos_apical, cos_lateral, cos_psi, sin_psi, alpha, beta, di_max, node_limit):
    """Iterations ``it_lo`` .. ``it_hi - 1`` of the guided growth (Guo et al. §5.2, Eq. 6-9).

    The sequential loop of :meth:`GuidedGrowth._grow`, compiled: per iteration
    every active marker finds its ``_K_BUDS`` nearest free buds within d_i
    (a uniform grid of cell d_i over the buds replaces the per-iteration
    ``cKDTree``; same strict ``d² < d_i²`` test and the same distance order)
    and goes to the first that perceives it (apical cone θ/2 for tips, lateral
    cone ψ + θ/2 otherwise); buds with markers grow one growth unit along
    V_A of Eq. 9; markers within d_k of a new node are killed; the stem's
    apical bud bridges gaps; buds with no marker within 12l are retired every
    8 iterations.  Its Python form (``py_func``, without numba) grows the
    same skeleton as the compiled one (tests/test_colonize_kernel.py; Sylva,
    not in the paper: an implementation detail).

    Node arrays are grown here when full and returned.  ``code``: 0 ran to
    ``it_hi``; 1 no marker left; 2 node limit; 3 no free bud; 4 stalled; 5 the
    roll-angle tables ``cos_tab``/``sin_tab`` are too short (nothing of
    iteration ``it`` was changed: enlarge them and call again from ``it``).
    """
    n = markers.shape[0]
    cap = pos.shape[0]
    # Static grid over the markers (for the kill and retirement searches).
    lo0 = markers[0, 0]
    lo1 = markers[0, 1]
    lo2 = markers[0, 2]
    hi0 = lo0
    hi1 = lo1
    hi2 = lo2
    for i in range(n):
        lo0 = min(lo0, markers[i, 0])
        lo1 = min(lo1, markers[i, 1])
        lo2 = min(lo2, markers[i, 2])
        hi0 = max(hi0, markers[i, 0])
        hi1 = max(hi1, markers[i, 1])
        hi2 = max(hi2, markers[i, 2])
    gs = max(dk, di_max / 4.0)
    while True:
        gx = int((hi0 - lo0) / gs) + 1
        gy = int((hi1 - lo1) / gs) + 1
        gz = int((hi2 - lo2) / gs) + 1
        if gx * gy * gz <= 4 * n + 4096:
            break
        gs *= 1.5
    ncell = gx * gy * gz
    mcell = np.empty(n, dtype=np.int64)
    mstart = np.zeros(ncell + 1, dtype=np.int64)
    for i in range(n):
        cx = min(max(int(np.floor((markers[i, 0] - lo0) / gs)), 0), gx - 1)
        cy = min(max(int(np.floor((markers[i, 1] - lo1) / gs)), 0), gy - 1)
        cz = min(max(int(np.floor((markers[i, 2] - lo2) / gs)), 0), gz - 1)
        c = (cx * gy + cy) * gz + cz
        mcell[i] = c
        mstart[c + 1] += 1
    for c in range(ncell):
        mstart[c + 1] += mstart[c]
    mfill = mstart[:-1].copy()
    morder = np.empty(n, dtype=np.int64)
    for i in range(n):
        c = mcell[i]
        morder[mfill[c]] = i
        mfill[c] += 1
    rk = int(np.ceil(dk / gs))
    rp = int(np.ceil(di_max / gs))
    dk2 = dk * dk
    dimax2 = di_max * di_max

    am = np.empty(n, dtype=np.int64)
    front = np.zeros(n, dtype=np.bool_)
    sel = np.empty(n, dtype=np.int64)
    selu = np.empty((n, 3))
    kb = _K_BUDS
    bd2 = np.empty(kb)
    bid = np.empty(kb, dtype=np.int64)

    code = 0
    it = it_lo
    while it < it_hi:
        n_act = 0
        for i in range(n):
            if active[i]:
                am[n_act] = i
                n_act += 1
        if n_act == 0:
            code = 1
            break
        if m > node_limit:
            code = 2
            break
        buds = np.empty(m, dtype=np.int64)
        nb = 0
        for j in range(m):
            if bud_free[j]:
                buds[nb] = j
                nb += 1
        if nb == 0:
            code = 3
            break
        di0 = di_of_t[it - 1]
        rho_units = di0 / l
        di = min(di0 * boost, di_max)
        di2 = di * di
        # Grid of cell >= d_i over the buds (clamped to the markers' box: still exact).
        bs = di
        while True:
            bx = int((hi0 - lo0) / bs) + 1
            by = int((hi1 - lo1) / bs) + 1
            bz = int((hi2 - lo2) / bs) + 1
            if bx * by * bz <= 4 * n + 4096:
                break
            bs *= 1.5
        nbc = bx * by * bz
        bstart = np.zeros(nbc + 1, dtype=np.int64)
        bcell = np.empty(nb, dtype=np.int64)
        for q in range(nb):
            j = buds[q]
            cx = min(max(int(np.floor((pos[j, 0] - lo0) / bs)), 0), bx - 1)
            cy = min(max(int(np.floor((pos[j, 1] - lo1) / bs)), 0), by - 1)
            cz = min(max(int(np.floor((pos[j, 2] - lo2) / bs)), 0), bz - 1)
            c = (cx * by + cy) * bz + cz
            bcell[q] = c
            bstart[c + 1] += 1
        for c in range(nbc):
            bstart[c + 1] += bstart[c]
        bfill = bstart[:-1].copy()
        border = np.empty(nb, dtype=np.int64)
        for q in range(nb):
            c = bcell[q]
            border[bfill[c]] = buds[q]
            bfill[c] += 1

        any_has = False
        for q in range(n_act):
            i = am[q]
            px = markers[i, 0]
            py = markers[i, 1]
            pz = markers[i, 2]
            cx = min(max(int(np.floor((px - lo0) / bs)), 0), bx - 1)
            cy = min(max(int(np.floor((py - lo1) / bs)), 0), by - 1)
            cz = min(max(int(np.floor((pz - lo2) / bs)), 0), bz - 1)
            cnt = 0
            for ix in range(max(cx - 1, 0), min(cx + 2, bx)):
                for iy in range(max(cy - 1, 0), min(cy + 2, by)):
                    for iz in range(max(cz - 1, 0), min(cz + 2, bz)):
                        c = (ix * by + iy) * bz + iz
                        for s in range(bstart[c], bstart[c + 1]):
                            j = border[s]
                            dx = px - pos[j, 0]
                            dy = py - pos[j, 1]
                            dz = pz - pos[j, 2]
                            d2 = dx * dx + dy * dy + dz * dz
                            if not d2 < di2:
                                continue
                            if cnt == kb and not d2 < bd2[kb - 1]:
                                continue
                            r = cnt if cnt < kb else kb - 1
                            while r > 0 and (d2 < bd2[r - 1] or (d2 == bd2[r - 1] and j < bid[r - 1])):
                                bd2[r] = bd2[r - 1]
                                bid[r] = bid[r - 1]
                                r -= 1
                            bd2[r] = d2
                            bid[r] = j
                            if cnt < kb:
                                cnt += 1
            front[i] = cnt > 0
            sel[q] = -1
            for r in range(cnt):
                j = bid[r]
                vx = px - pos[j, 0]
                vy = py - pos[j, 1]
                vz = pz - pos[j, 2]
                nrm = np.sqrt((vx * vx + vz * vz) + vy * vy)       # einsum's order
                den = max(nrm, 1e-12)
                ux = vx / den
                uy = vy / den
                uz = vz / den
                cmin = cos_apical if (n_children[j] == 0 and not seed[j]) else cos_lateral
                if nrm > 1e-9 and (ux * heading[j, 0] + uz * heading[j, 2]) + uy * heading[j, 1] > cmin:
                    sel[q] = j
                    selu[q, 0] = ux
                    selu[q, 1] = uy
                    selu[q, 2] = uz
                    any_has = True
                    break

        if not any_has:
            # No bud perceives a marker: the stem's apical bud bridges (L-system 1, rule 2).
            zmax = markers[am[0], 2]
            for q in range(n_act):
                zmax = max(zmax, markers[am[q], 2])
            tips = np.empty(m, dtype=np.int64)
            nt = 0
            for j in range(m):
                if leader[j] and n_children[j] == 0 and bud_free[j] and pos[j, 2] < zmax:
                    tips[nt] = j
                    nt += 1
            if nt > 0 and boost == 1.0:
                ku = max(1, int(rho_units))
                need = m + nt * ku
                if need > cap:
                    cap = max(need, 2 * cap)
                    pos, heading, parent, n_children, seed, bud_free, added, leader = grown_nodes(
                        cap, m, pos, heading, parent, n_children, seed, bud_free, added, leader)
                first_new = m
                for t in range(nt):
                    j = tips[t]
                    hx = heading[j, 0] + 0.0
                    hy = heading[j, 1] + 0.0
                    hz = heading[j, 2] + 1.0
                    hn = np.sqrt(hx * hx + hy * hy + hz * hz)
                    if hn > 1e-12:
                        hd = max(hn, 1e-12)
                        hx = hx / hd
                        hy = hy / hd
                        hz = hz / hd
                    else:
                        hx = 0.0
                        hy = 0.0
                        hz = 0.0
                    prev = j
                    for k in range(1, ku + 1):
                        step = l * k
                        pos[m, 0] = pos[j, 0] + step * hx
                        pos[m, 1] = pos[j, 1] + step * hy
                        pos[m, 2] = pos[j, 2] + step * hz
                        heading[m, 0] = hx
                        heading[m, 1] = hy
                        heading[m, 2] = hz
                        parent[m] = prev
                        n_children[m] = 0
                        n_children[prev] += 1
                        seed[m] = True
                        added[m] = True
                        bud_free[m] = True
                        leader[m] = True
                        prev = m
                        m += 1
                    bud_free[j] = True
                for q in range(first_new, m):
                    cx = min(max(int(np.floor((pos[q, 0] - lo0) / gs)), 0), gx - 1)
                    cy = min(max(int(np.floor((pos[q, 1] - lo1) / gs)), 0), gy - 1)
                    cz = min(max(int(np.floor((pos[q, 2] - lo2) / gs)), 0), gz - 1)
                    for ix in range(max(cx - rk, 0), min(cx + rk + 1, gx)):
                        for iy in range(max(cy - rk, 0), min(cy + rk + 1, gy)):
                            for iz in range(max(cz - rk, 0), min(cz + rk + 1, gz)):
                                c = (ix * gy + iy) * gz + iz
                                for s in range(mstart[c], mstart[c + 1]):
                                    i = morder[s]
                                    if active[i]:
                                        dx = markers[i, 0] - pos[q, 0]
                                        dy = markers[i, 1] - pos[q, 1]
                                        dz = markers[i, 2] - pos[q, 2]
                                        if dx * dx + dy * dy + dz * dz < dk2:
                                            active[i] = False
                it += 1
                continue
            stall += 1
            if stall >= _STALL_LIMIT:
                code = 4
                break
            boost *= 1.5
            it += 1
            continue

        # Growth (Eq. 9 and one growth unit per growing bud).  Nothing is changed
        # before the new nodes are added, so code 5 can return cleanly.
        sums = np.zeros((m, 3))
        csum = np.zeros((m, 3))
        wsum = np.zeros(m)
        for q in range(n_act):
            j = sel[q]
            if j < 0:
                continue
            i = am[q]
            w = weight[i]
            sums[j, 0] += w * selu[q, 0]
            sums[j, 1] += w * selu[q, 1]
            sums[j, 2] += w * selu[q, 2]
            wsum[j] += w
            csum[j, 0] += w * markers[i, 0]
            csum[j, 1] += w * markers[i, 1]
            csum[j, 2] += w * markers[i, 2]
        grow = np.empty(m, dtype=np.int64)
        ng = 0
        for j in range(m):
            if wsum[j] > 0:
                grow[ng] = j
                ng += 1
        vnew = np.empty((ng, 3))
        units = np.empty(ng, dtype=np.int64)
        tipg = np.empty(ng, dtype=np.bool_)
        maxu = max(1, int(rho_units))
        short = False
        for g in range(ng):
            j = grow[g]
            ws = wsum[j]
            o0 = sums[j, 0] / ws
            o1 = sums[j, 1] / ws
            o2 = sums[j, 2] / ws
            h0 = heading[j, 0]
            h1 = heading[j, 1]
            h2 = heading[j, 2]
            is_tip = n_children[j] == 0
            tipg[g] = is_tip
            dd = o0 * h0 + o1 * h1 + o2 * h2
            a0 = o0 - dd * h0
            a1 = o1 - dd * h1
            a2 = o2 - dd * h2
            if np.sqrt(a0 * a0 + a1 * a1 + a2 * a2) < 1e-6:
                # No azimuth from the markers: the roll angle φ (Table 2).
                if abs(h2) < 0.9:
                    r0 = 0.0
                    r1 = 0.0
                    r2 = 1.0
                else:
                    r0 = 1.0
                    r1 = 0.0
                    r2 = 0.0
                e0 = h1 * r2 - h2 * r1
                e1 = h2 * r0 - h0 * r2
                e2 = h0 * r1 - h1 * r0
                en = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
                if en > 1e-12:
                    ed = max(en, 1e-12)
                    e0 = e0 / ed
                    e1 = e1 / ed
                    e2 = e2 / ed
                else:
                    e0 = 0.0
                    e1 = 0.0
                    e2 = 0.0
                f0 = h1 * e2 - h2 * e1
                f1 = h2 * e0 - h0 * e2
                f2 = h0 * e1 - h1 * e0
                ia = j + n_children[j]
                if ia >= cos_tab.shape[0]:
                    short = True
                    break
                ca = cos_tab[ia]
                sa = sin_tab[ia]
                a0 = ca * e0 + sa * f0
                a1 = ca * e1 + sa * f1
                a2 = ca * e2 + sa * f2
            an = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
            if an > 1e-12:
                ad = max(an, 1e-12)
                a0 = a0 / ad
                a1 = a1 / ad
                a2 = a2 / ad
            else:
                a0 = 0.0
                a1 = 0.0
                a2 = 0.0
            if is_tip:
                d0 = h0
                d1 = h1
                d2_ = h2
            else:
                d0 = cos_psi * h0 + sin_psi * a0
                d1 = cos_psi * h1 + sin_psi * a1
                d2_ = cos_psi * h2 + sin_psi * a2
            v0 = d0 + alpha * o0 + beta * 0.0
            v1 = d1 + alpha * o1 + beta * 0.0
            v2 = d2_ + alpha * o2 + beta * -1.0
            vn = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
            if vn > 1e-9:
                vd = max(vn, 1e-12)
                v0 = v0 / vd
                v1 = v1 / vd
                v2 = v2 / vd
            else:
                v0 = d0
                v1 = d1
                v2 = d2_
            vnew[g, 0] = v0
            vnew[g, 1] = v1
            vnew[g, 2] = v2
            c0 = csum[j, 0] / ws - pos[j, 0]
            c1 = csum[j, 1] / ws - pos[j, 1]
            c2 = csum[j, 2] / ws - pos[j, 2]
            reach = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
            u = np.rint(reach / l)
            if u < 1.0:
                u = 1.0
            if u > maxu:
                u = float(maxu)
            units[g] = int(u)
        if short:
            code = 5
            break
        stall = 0
        boost = 1.0
        total = 0
        umax = 0
        for g in range(ng):
            total += units[g]
            umax = max(umax, units[g])
        need = m + total
        if need > cap:
            cap = max(need, 2 * cap)
            pos, heading, parent, n_children, seed, bud_free, added, leader = grown_nodes(
                cap, m, pos, heading, parent, n_children, seed, bud_free, added, leader)
        first_new = m
        for g in range(ng):
            j = grow[g]
            lead = tipg[g] and leader[j]
            prev = j
            for k in range(1, units[g] + 1):
                step = l * k
                pos[m, 0] = pos[j, 0] + step * vnew[g, 0]
                pos[m, 1] = pos[j, 1] + step * vnew[g, 1]
                pos[m, 2] = pos[j, 2] + step * vnew[g, 2]
                heading[m, 0] = vnew[g, 0]
                heading[m, 1] = vnew[g, 1]
                heading[m, 2] = vnew[g, 2]
                parent[m] = prev
                n_children[m] = 0
                n_children[prev] += 1
                seed[m] = False
                added[m] = False
                bud_free[m] = True
                leader[m] = lead
                prev = m
                m += 1
        # A node's buds are spent once it has its apical and one lateral child.
        for g in range(ng):
            j = grow[g]
            bud_free[j] = n_children[j] < 2
        # Kill markers within d_k of the new nodes (the front suffices when d_k + shoot <= d_i).
        only_front = dk + l * umax <= di
        for q in range(first_new, m):
            cx = min(max(int(np.floor((pos[q, 0] - lo0) / gs)), 0), gx - 1)
            cy = min(max(int(np.floor((pos[q, 1] - lo1) / gs)), 0), gy - 1)
            cz = min(max(int(np.floor((pos[q, 2] - lo2) / gs)), 0), gz - 1)
            for ix in range(max(cx - rk, 0), min(cx + rk + 1, gx)):
                for iy in range(max(cy - rk, 0), min(cy + rk + 1, gy)):
                    for iz in range(max(cz - rk, 0), min(cz + rk + 1, gz)):
                        c = (ix * gy + iy) * gz + iz
                        for s in range(mstart[c], mstart[c + 1]):
                            i = morder[s]
                            if active[i] and (front[i] or not only_front):
                                dx = markers[i, 0] - pos[q, 0]
                                dy = markers[i, 1] - pos[q, 1]
                                dz = markers[i, 2] - pos[q, 2]
                                if dx * dx + dy * dy + dz * dz < dk2:
                                    active[i] = False
        # Buds with no active marker within the largest influence distance never grow again
        # (except the stem's apical tip, which may still bridge a gap).
        if it % 8 == 0:
            left = False
            for i in range(n):
                if active[i]:
                    left = True
                    break
            if left:
                for j in range(m):
                    if not bud_free[j] or (leader[j] and n_children[j] == 0):
                        continue
                    cx = min(max(int(np.floor((pos[j, 0] - lo0) / gs)), 0), gx - 1)
                    cy = min(max(int(np.floor((pos[j, 1] - lo1) / gs)), 0), gy - 1)
                    cz = min(max(int(np.floor((pos[j, 2] - lo2) / gs)), 0), gz - 1)
                    found = False
                    for ix in range(max(cx - rp, 0), min(cx + rp + 1, gx)):
                        for iy in range(max(cy - rp, 0), min(cy + rp + 1, gy)):
                            for iz in range(max(cz - rp, 0), min(cz + rp + 1, gz)):
                                c = (ix * gy + iy) * gz + iz
                                for s in range(mstart[c], mstart[c + 1]):
                                    i = morder[s]
                                    if active[i]:
                                        dx = markers[i, 0] - pos[j, 0]
                                        dy = markers[i, 1] - pos[j, 1]
                                        dz = markers[i, 2] - pos[j, 2]
                                        if dx * dx + dy * dy + dz * dz < dimax2:
                                            found = True
                                            break
                                if found:
                                    break
                            if found:
                                break
                        if found:
                            break
                    if not found:
                        bud_free[j] = False
        it += 1
    return (pos, heading, parent, n_children, seed, bud_free, added, leader, m, stall, boost, it, code)


def roll_tables(roll: float, size: int):
    """cos and sin of the roll angle φ·j, j < ``size`` (lateral bud j + its children, Table 2's φ).

    Computed by numpy outside the kernel, so that the compiled kernel and its
    Python form read the same values (numpy's vectorised cos/sin may differ
    from libm's in the last bit).
    """
    ang = roll * np.arange(size)
    return np.cos(ang), np.sin(ang)


class Nodes:
    """Growable node arrays (amortised doubling); parents always before children."""

    def __init__(self, cap: int = 256):
        self.m = 0
        self.pos = np.zeros((cap, 3))
        self.heading = np.zeros((cap, 3))
        self.parent = np.full(cap, -1, dtype=np.int64)
        self.n_children = np.zeros(cap, dtype=np.int64)
        self.seed = np.zeros(cap, dtype=bool)        # roots/trunk: lateral cone from the start
        self.bud_free = np.zeros(cap, dtype=bool)
        self.added = np.zeros(cap, dtype=bool)
        self.leader = np.zeros(cap, dtype=bool)      # on the stem's apical line (root upwards)

    def add(self, pos, heading, parent, seed=False, added=False, buds=True, leader=False):
        pos = np.asarray(pos, dtype=np.float64).reshape(-1, 3)
        k = len(pos)
        need = self.m + k
        if need > len(self.pos):
            cap = max(need, 2 * len(self.pos))
            for name in ("pos", "heading", "parent", "n_children", "seed", "bud_free", "added", "leader"):
                old = getattr(self, name)
                new = np.zeros((cap,) + old.shape[1:], dtype=old.dtype)
                if name == "parent":
                    new[:] = -1
                new[:self.m] = old[:self.m]
                setattr(self, name, new)
        s = slice(self.m, need)
        self.pos[s] = pos
        self.heading[s] = np.asarray(heading, dtype=np.float64).reshape(-1, 3)
        self.parent[s] = parent
        self.seed[s] = seed
        self.added[s] = added
        self.bud_free[s] = buds
        self.leader[s] = leader
        par = np.atleast_1d(np.asarray(parent, dtype=np.int64))
        par = par[par >= 0]
        if len(par):
            np.add.at(self.n_children, par, 1)
        first = self.m
        self.m = need
        return np.arange(first, need)
