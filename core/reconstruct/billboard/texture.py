"""Billboard textures: Zhou et al. 2013, "Automatic reconstruction of lightweight trees" §VI-B.

The crown's pixels cleaned by a Gaussian mixture in HSV (:func:`gmm_clean`; hue as a point on the HSV cone
and the EM in a few vectorised lines are Sylva's), and removed or unknown pixels filled block by block
(:func:`complete_blocks`: Algorithm 1, cost Eq. 2 with the Bhattacharyya histogram distance Eq. 3).
``method`` is a :class:`~.tree.Billboard`.
"""
from __future__ import annotations

import math
from typing import Optional, Tuple

import numpy as np


# --------------------------------------------------------------------------- §VI-B textures

def _hsv_cone(rgb: np.ndarray) -> np.ndarray:
    """RGB [0, 1] (n, 3) -> HSV as points on the cone (s cos 2πh, s sin 2πh, v), (n, 3)."""
    return _hsv_cone_rows(rgb).T


def _hsv_cone_rows(rgb: np.ndarray) -> np.ndarray:
    """:func:`_hsv_cone` as (3, n) rows (contiguous: fast elementwise work)."""
    r, g, b = np.array(rgb, dtype=np.float64).T.copy()
    mx = np.maximum(np.maximum(r, g), b)
    d = mx - np.minimum(np.minimum(r, g), b)
    is_r, is_g = mx == r, mx == g
    safe = np.where(d > 0, d, 1.0)
    h = np.where(is_r, g - b, np.where(is_g, b - r, r - g)) / safe
    h = np.where(is_r, h % 6.0, h + np.where(is_g, 2.0, 4.0))
    h = np.where(d > 0, h / 6.0, 0.0)
    s = np.where(mx > 0, d / np.where(mx > 0, mx, 1.0), 0.0)
    angle = 2 * np.pi * h
    out = np.empty((3, len(r)))
    out[0], out[1], out[2] = s * np.cos(angle), s * np.sin(angle), mx
    return out


def _gmm_diag(xt: np.ndarray, components: int, seed: int, max_iter: int = 50, tol: float = 1e-3,
              reg_covar: float = 1e-4):
    """EM for a Gaussian mixture with diagonal covariances on the samples ``xt`` (d, n): (weights, means, variances).

    The EM of scikit-learn's ``GaussianMixture(covariance_type="diag", init_params="k-means++")``
    step for step (its k-means++ seeds, E-step then M-step, stop when the mean log-likelihood
    changes by less than ``tol``), without its per-iteration overhead.
    """
    from sklearn.cluster import kmeans_plusplus

    n = xt.shape[1]
    k = int(components)
    tiny = 10 * np.finfo(np.float64).eps
    x2 = xt * xt
    _, seeds = kmeans_plusplus(np.ascontiguousarray(xt.T), k, random_state=int(seed) % (2**31))
    means = xt[:, seeds].T                     # one-hot responsibilities on the seeds
    var = x2[:, seeds].T - means * means + reg_covar
    weights = np.full(k, (1.0 + tiny) / n)
    bound = -np.inf
    for _ in range(int(max_iter)):
        log_p = _gmm_log_prob(xt, weights, means, var)                         # E-step, (k, n)
        top = log_p.max(axis=0)
        log_norm = top + np.log(np.exp(log_p - top).sum(axis=0))
        resp = np.exp(log_p - log_norm)
        nk = resp.sum(axis=1) + tiny                                           # M-step
        weights = nk / nk.sum()
        means = np.einsum("kn,dn->kd", resp, xt) / nk[:, None]
        var = np.einsum("kn,dn->kd", resp, x2) / nk[:, None] - means * means + reg_covar
        new_bound = float(log_norm.mean())
        if abs(new_bound - bound) < tol:
            break
        bound = new_bound
    return weights, means, var


def _gmm_log_prob(xt: np.ndarray, weights: np.ndarray, means: np.ndarray, var: np.ndarray) -> np.ndarray:
    """(k, n) log(w_k N(x | mean_k, diag var_k)) of the samples ``xt`` (d, n)."""
    const = np.log(weights) - 0.5 * (len(xt) * np.log(2 * np.pi) + np.log(var).sum(axis=1))
    inv = 1.0 / var
    diff = xt[None, :, :] - means[:, :, None]          # (k, d, n): elementwise, not BLAS (its threads spin)
    diff *= diff
    diff *= inv[:, :, None]
    return const[:, None] - 0.5 * diff.sum(axis=1)


def gmm_clean(rgb: np.ndarray, components: int, seed: int, max_samples: int = 1500) -> np.ndarray:
    """§VI-B: True for colours of the right cluster (GMM + EM in HSV; the cluster nearest the mean HSV).

    The mixture is fitted on at most ``max_samples`` colours (a seeded random sample) and predicted on all.
    Sylva, not in the paper (speed): EM is :func:`_gmm_diag`, scikit-learn's ``GaussianMixture``
    algorithm in a few vectorised lines (the class spends ~0.6 ms an iteration in overhead).
    """
    n = len(rgb)
    if components < 2 or n < 10 * components:
        return np.ones(n, dtype=bool)
    feats = _hsv_cone_rows(rgb)                                                   # (3, n)
    rng = np.random.default_rng(seed)
    train = feats if n <= max_samples else feats[:, np.sort(rng.choice(n, max_samples, replace=False))]
    weights, means, var = _gmm_diag(train, int(components), seed)
    labels = np.argmax(_gmm_log_prob(feats, weights, means, var), axis=0)
    right = int(np.argmin(np.linalg.norm(means - feats.mean(axis=1), axis=1)))
    return labels == right


def bhattacharyya(h1: np.ndarray, h2: np.ndarray) -> np.ndarray:
    """Eq. 3: d(H1, H2) = sqrt(1 - Σ sqrt(H1 H2) / sqrt(mean(H1) mean(H2) N²)), broadcast over leading axes."""
    n = h1.shape[-1]
    norm = np.sqrt(h1.mean(axis=-1) * h2.mean(axis=-1) * n * n)
    bc = np.sqrt(h1 * h2).sum(axis=-1) / np.where(norm > 0, norm, 1.0)
    return np.sqrt(np.clip(1.0 - bc, 0.0, 1.0))


def _hist(pixels: np.ndarray, bins: int) -> np.ndarray:
    """Per-channel histograms of (..., m, 3) colours in [0, 1], concatenated: (..., 3 bins)."""
    q = np.clip((pixels * bins).astype(np.int64), 0, bins - 1) + np.arange(3) * bins
    lead = q.shape[:-2]
    flat = q.reshape(-1, q.shape[-2] * 3)
    k = flat.shape[0]
    idx = (flat + (np.arange(k) * (3 * bins))[:, None]).ravel()
    out = np.bincount(idx, minlength=k * 3 * bins).astype(np.float64)
    return out.reshape(*lead, 3 * bins)


def complete_blocks(image: np.ndarray, mask: np.ndarray, good: np.ndarray, method: "Billboard",
                    rng: Optional[np.random.Generator] = None) -> Tuple[np.ndarray, int]:
    """Algorithm 1 (§VI-B): fill the mask pixels that are not ``good`` block by block.

    Tiling blocks of size s get L = 2 (no mask pixel), 0 (to replace: more
    than ``max_bad_fraction`` of its mask pixels are wrong or unknown) or 1;
    the few wrong pixels of an L = 1 block take the colour of the nearest
    correct pixel (Sylva's reading of "the texture is correct": point colours
    cleaned by the GMM leave scattered holes, not only whole wrong regions).
    Candidate blocks T_j are s x s windows (stride s/2) inside the mask with
    at most half that share of wrong pixels; s starts at ``block_px`` and
    halves until there is one.  While a block has L = 0, the one with most
    L = 1 4-neighbours is replaced by the candidate minimising Eq. 2:
    Σ_neighbours Bhattacharyya (Eq. 3) of the RGB histograms + the SSD of
    RGB (0..1) across the shared boundary (with no L = 1 neighbour: the
    candidate nearest the mean histogram).  Returns (completed image, s);
    s = 0 when no pixel is correct (the caller draws a procedural texture).

    Sylva, not in the paper (speed, same result inside the mask): the work is done in the mask's bounding
    box plus one pixel, its corner on the block grid; pixels outside it keep their colour.
    """
    h, w, _ = image.shape
    good = good & mask
    need = mask & ~good
    if not need.any():
        return image, int(method.block_px)
    if not good.any():
        return image, 0
    align, s = 1, int(method.block_px)
    while s >= 1:                                  # every block size and candidate stride tried below
        align = math.lcm(align, s, max(1, s // 2))
        s //= 2
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    r0, c0 = max(0, int(rows[0]) - 1) // align * align, max(0, int(cols[0]) - 1) // align * align
    r1 = min(h, r0 + -(-(int(rows[-1]) + 2 - r0) // align) * align)
    c1 = min(w, c0 + -(-(int(cols[-1]) + 2 - c0) // align) * align)
    if (r0, c0, r1, c1) == (0, 0, h, w):
        return _complete_window(image, mask, good, need, method)
    sub, s = _complete_window(image[r0:r1, c0:c1], mask[r0:r1, c0:c1], good[r0:r1, c0:c1], need[r0:r1, c0:c1],
                              method)
    out = image.copy()
    out[r0:r1, c0:c1] = sub
    return out, s


def _complete_window(image: np.ndarray, mask: np.ndarray, good: np.ndarray, need: np.ndarray, method: "Billboard"):
    """:func:`complete_blocks` on a window holding the whole mask."""
    from scipy import ndimage

    h, w, _ = image.shape
    ri, ci = ndimage.distance_transform_edt(~good, return_distances=False, return_indices=True)
    img = np.take(image.reshape(h * w, 3), (ri * w + ci).ravel(), axis=0).reshape(h, w, 3)  # wrong: nearest correct
    limit = float(method.max_bad_fraction)
    s = int(method.block_px)
    cand = None
    while s >= 1:
        if h >= s and w >= s:
            win_m = _window_sum(mask, s) == s * s
            win_bad = _window_sum(need, s) / float(s * s)
            step = max(1, s // 2)
            ok = (win_m & (win_bad <= limit / 2.0))[::step, ::step]
            ii, jj = np.nonzero(ok)
            if len(ii):
                ii, jj = ii * step, jj * step
                if len(ii) > method.max_candidates:
                    pick = np.linspace(0, len(ii) - 1, method.max_candidates).round().astype(int)
                    ii, jj = ii[pick], jj[pick]
                cand = (ii, jj)
                break
        s //= 2
    if cand is None:
        return img, 0
    H, W = -(-h // s), -(-w // s)
    padded = np.zeros((H * s, W * s, 3))
    padded[:h, :w] = img
    pm = np.zeros((H * s, W * s), bool)
    pm[:h, :w] = mask
    pn = np.zeros((H * s, W * s), bool)
    pn[:h, :w] = need
    n_mask = pm.reshape(H, s, W, s).sum(axis=(1, 3))
    n_bad = pn.reshape(H, s, W, s).sum(axis=(1, 3))
    L = np.where(n_mask == 0, 2, np.where(n_bad > limit * np.maximum(n_mask, 1), 0, 1))
    if not (L == 0).any():
        return img, s
    ci_, cj_ = cand
    windows = np.lib.stride_tricks.sliding_window_view(img, (s, s), axis=(0, 1))  # (h-s+1, w-s+1, 3, s, s)
    tiles = windows[ci_, cj_].transpose(0, 2, 3, 1)                                 # (n, s, s, 3)
    bins = int(method.hist_bins)
    # Eq. 3 on histograms normalised to sum 1: the normaliser is 1 and d = sqrt(1 - Σ sqrt(h1 h2))
    t_hist = _hist(tiles.reshape(len(ci_), s * s, 3), bins)
    t_root = np.sqrt(t_hist / t_hist.sum(axis=1, keepdims=True))
    blk = padded.reshape(H, s, W, s, 3).transpose(0, 2, 1, 3, 4).copy()          # (H, W, s, s, 3)
    # histograms of the L = 1 blocks next to an L = 0 block (the only ones Eq. 2 reads; replaced blocks take
    # their candidate's)
    zero = L == 0
    near = np.zeros_like(zero)
    near[1:] |= zero[:-1]
    near[:-1] |= zero[1:]
    near[:, 1:] |= zero[:, :-1]
    near[:, :-1] |= zero[:, 1:]
    bi_, bj_ = np.nonzero(near & (L == 1))
    b_root = np.zeros((H, W, 3 * bins))
    if len(bi_):
        b_hist = _hist(blk[bi_, bj_].reshape(len(bi_), s * s, 3), bins)
        b_root[bi_, bj_] = np.sqrt(b_hist / np.maximum(b_hist.sum(axis=1, keepdims=True), 1e-12))
    g_root = np.sqrt(t_hist.sum(axis=0) / t_hist.sum())
    n_cand = len(ci_)
    # Eq. 2's boundary SSD with each side's L = 1 neighbour: Σ (t - b)² = Σ t² - 2 Σ t b + Σ b², the candidates'
    # sides side by side so that one product serves all neighbours
    sides = ((-1, 0, tiles[:, 0], lambda b: b[-1]), (1, 0, tiles[:, -1], lambda b: b[0]),
             (0, -1, tiles[:, :, 0], lambda b: b[:, -1]), (0, 1, tiles[:, :, -1], lambda b: b[:, 0]))
    t_side = np.concatenate([t.reshape(n_cand, 3 * s) for _, _, t, _ in sides], axis=1)     # (n, 4 * 3s)
    t_side_sq = (t_side * t_side).reshape(n_cand, 4, 3 * s).sum(axis=2)                      # (n, 4)
    ones = (L == 1).astype(np.int64)
    deg = np.zeros_like(ones)                 # L = 1 4-neighbours of every L = 0 block (-1: not to replace)
    deg[1:] += ones[:-1]
    deg[:-1] += ones[1:]
    deg[:, 1:] += ones[:, :-1]
    deg[:, :-1] += ones[:, 1:]
    deg = np.where(L == 0, deg, -1)
    flat_deg = deg.ravel()
    g_cost = None
    todo = int((L == 0).sum())
    for _ in range(todo):
        bi, bj = divmod(int(np.argmax(flat_deg)), W)
        present, vec, b_sq = [], np.zeros(4 * 3 * s), 0.0
        for e, (di, dj, _, b_edge) in enumerate(sides):
            ni, nj = bi + di, bj + dj
            if 0 <= ni < H and 0 <= nj < W and L[ni, nj] == 1:
                b = b_edge(blk[ni, nj]).ravel()
                vec[e * 3 * s:(e + 1) * 3 * s] = b
                b_sq += float(b @ b)
                present.append((e, ni, nj))
        if present:
            e_, ni_, nj_ = (list(v) for v in zip(*present))
            cost = np.sqrt(np.clip(1.0 - t_root @ b_root[ni_, nj_].T, 0.0, 1.0)).sum(axis=1)    # Eq. 3
            cost += t_side_sq[:, e_].sum(axis=1) - 2.0 * (t_side @ vec) + b_sq
        else:                                  # no L = 1 neighbour: nearest the mean histogram
            if g_cost is None:
                g_cost = np.sqrt(np.clip(1.0 - t_root @ g_root, 0.0, 1.0))
            cost = g_cost
        best = int(np.argmin(cost))
        blk[bi, bj] = tiles[best]
        b_root[bi, bj] = t_root[best]
        L[bi, bj] = 1
        deg[bi, bj] = -1
        for di, dj in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            ni, nj = bi + di, bj + dj
            if 0 <= ni < H and 0 <= nj < W and L[ni, nj] == 0:
                deg[ni, nj] += 1
    out = blk.transpose(0, 2, 1, 3, 4).reshape(H * s, W * s, 3)[:h, :w]
    return _paste(img, out, need, n_bad, n_mask, limit, s, h, w), s


def _window_sum(a: np.ndarray, s: int) -> np.ndarray:
    """Sums of every s x s window of a 2D array (summed-area table), shape (h - s + 1, w - s + 1)."""
    c = np.zeros((a.shape[0] + 1, a.shape[1] + 1))
    c[1:, 1:] = np.cumsum(np.cumsum(a, axis=0, dtype=np.float64), axis=1)
    return c[s:, s:] - c[:-s, s:] - c[s:, :-s] + c[:-s, :-s]


def _paste(img, out, need, n_bad, n_mask, limit, s, h, w):
    """Copy the replaced blocks (those that had L = 0) of ``out`` into ``img`` inside the mask."""
    was0 = n_bad > limit * np.maximum(n_mask, 1)
    sel = np.repeat(np.repeat(was0, s, axis=0), s, axis=1)[:h, :w]
    res = img.copy()
    res[sel] = out[sel]
    return res
