"""Which Python packages Sylva needs, and how to tell a user what is missing.

Kept free of qgis and of the packages it checks, so it runs in any Python.
"""
from __future__ import annotations

import importlib.util
import sys
from typing import List, Tuple

# import name -> PyPI name
REQUIRED: Tuple[Tuple[str, str], ...] = (
    ("numpy", "numpy<2"),
    ("scipy", "scipy"),
    ("laspy", "laspy"),
    ("lazrs", "lazrs"),
    ("pyproj", "pyproj"),
    ("shapely", "shapely>=2"),
    ("sklearn", "scikit-learn"),
    ("trimesh", "trimesh"),
    ("tifffile", "tifffile"),
    ("geographiclib", "geographiclib"),
    ("lxml", "lxml"),
    ("PIL", "pillow"),
    ("numba", "numba<0.62"),
)


def missing() -> List[str]:
    """PyPI names of the required packages that cannot be imported."""
    return [pip for module, pip in REQUIRED if importlib.util.find_spec(module) is None]


def install_hint(packages: List[str]) -> str:
    """A sentence a user can act on, naming the packages and the exact command."""
    quoted = " ".join(f'"{p}"' if "<" in p or ">" in p else p for p in packages)
    return (
        f"Sylva needs these Python packages in the Python that QGIS uses: {', '.join(packages)}. "
        f"Install them from a terminal with:  {sys.executable if 'python' in sys.executable else 'python3'} "
        f"-m pip install --user {quoted}  (on Debian/Ubuntu add --break-system-packages), "
        "then restart QGIS."
    )
