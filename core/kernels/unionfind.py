"""Disjoint sets over an int array of parents (union-find with path halving), for kernels that join parts."""
from __future__ import annotations

from ..jit import helper

__all__ = ["uf_find", "uf_union"]


@helper
def uf_find(root, a):
    """The representative of ``a``'s set; halves the path on the way (``root[i] == i`` marks a root)."""
    while root[a] != a:
        root[a] = root[root[a]]
        a = root[a]
    return a


@helper
def uf_union(root, a, b):
    """Join the sets of ``a`` and ``b`` under the smaller representative; False when already one set."""
    a = uf_find(root, a)
    b = uf_find(root, b)
    if a == b:
        return False
    if a < b:
        root[b] = a
    else:
        root[a] = b
    return True
