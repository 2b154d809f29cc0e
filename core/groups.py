"""Per-group statistics of points (labels 0..n-1) by ``np.bincount``: no sort, no Python loop over groups."""
from __future__ import annotations

from typing import Tuple

import numpy as np


def group_means(xyz: np.ndarray, labels: np.ndarray, n: int) -> Tuple[np.ndarray, np.ndarray]:
    """((n, d) mean of each group's points, (n,) float count); an empty group's mean is 0."""
    counts = np.bincount(labels, minlength=n).astype(np.float64)
    c = np.empty((n, xyz.shape[1]))
    for j in range(xyz.shape[1]):
        c[:, j] = np.bincount(labels, weights=xyz[:, j], minlength=n)
    return c / np.maximum(counts, 1.0)[:, None], counts


def group_covariances(xyz: np.ndarray, labels: np.ndarray, n: int) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """((n, d, d) covariance (divided by the count) of each group's points about its mean, the
    means, the counts), as :func:`group_means` gives them."""
    mean, counts = group_means(xyz, labels, n)
    d = xyz - mean[labels]
    dim = xyz.shape[1]
    cov = np.empty((n, dim, dim))
    for i in range(dim):
        for j in range(i, dim):
            cov[:, i, j] = cov[:, j, i] = np.bincount(labels, weights=d[:, i] * d[:, j], minlength=n)
    cov /= np.maximum(counts, 1.0)[:, None, None]
    return cov, mean, counts
