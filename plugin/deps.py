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


def interpreter() -> str:
    """The Python interpreter that runs this code, as a command a user can type.

    Inside QGIS ``sys.executable`` is the QGIS binary (``/usr/bin/qgis``, ``qgis-bin.exe``), not a Python:
    the interpreter QGIS embeds is found from ``sys.exec_prefix`` and the running version
    (``/usr/bin/python3.11`` on Debian 12, ``python3.exe`` in OSGeo4W's ``apps/Python3x``)."""
    import os
    import shutil
    from pathlib import Path

    exe = Path(sys.executable or "")
    if exe.name.lower().startswith("python"):
        return str(exe)
    major, minor = sys.version_info[:2]
    prefixes = [Path(sys.prefix), Path(sys.exec_prefix), Path(getattr(sys, "base_exec_prefix", sys.exec_prefix))]
    names = ([f"python{major}.{minor}.exe", "python3.exe", "python.exe"] if os.name == "nt"
             else [f"python{major}.{minor}", f"python{major}"])
    for prefix in prefixes:
        for folder in (prefix / "bin", prefix):
            for name in names:
                candidate = folder / name
                if candidate.is_file() and os.access(candidate, os.X_OK):
                    return str(candidate)
    found = shutil.which(f"python{major}.{minor}")
    return found or f"python{major}.{minor}"


def pip_command(packages: List[str]) -> str:
    """The exact command that installs ``packages`` into the Python QGIS runs."""
    quoted = " ".join(f'"{p}"' if "<" in p or ">" in p else p for p in packages)
    if sys.prefix != getattr(sys, "base_prefix", sys.prefix):   # a virtual environment: install into it
        return f"{interpreter()} -m pip install {quoted}"
    command = f"{interpreter()} -m pip install --user {quoted}"
    if _externally_managed():
        command += " --break-system-packages"   # Debian/Ubuntu's system Python refuses --user installs otherwise
    return command


def _externally_managed() -> bool:
    import sysconfig
    from pathlib import Path

    try:
        return (Path(sysconfig.get_paths()["stdlib"]) / "EXTERNALLY-MANAGED").is_file()
    except (KeyError, OSError):   # pragma: no cover
        return False


def install_hint(packages: List[str]) -> str:
    """A sentence a user can act on, naming the packages and the exact command."""
    return (
        f"Sylva needs these Python packages in the Python that QGIS uses ({interpreter()}, Python "
        f"{sys.version_info[0]}.{sys.version_info[1]}): {', '.join(packages)}. "
        f"Install them from a terminal with:  {pip_command(packages)}  then restart QGIS."
    )
