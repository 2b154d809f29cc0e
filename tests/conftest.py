"""Shared fixtures: the bundled sample, the shared real data, QGIS with Sylva's provider."""
from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "resources" / "sample" / "sample.laz"
SAMPLE_TRUTH = ROOT / "resources" / "sample" / "sample_trees.csv"
SHARED_DATA = ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def sample_laz() -> Path:
    assert SAMPLE.exists(), "the bundled sample tile is missing: python scripts/make_sample.py writes it"
    return SAMPLE


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent")
    return SHARED_DATA


def segmented_corner_of(sample: Path, folder: Path, size_m: float):
    """A size_m x size_m corner of the sample, segmented (NormalizedCut), written as LAZ with a treeID.

    Returns (path, labels)."""
    from sylva.core.io import read_cloud
    from sylva.core.io.las import write_las
    from sylva.core.segment import segment_trees
    from sylva.core.terrain import normalize

    cloud = read_cloud(sample)
    x0, y0 = cloud.xyz[:, 0].min(), cloud.xyz[:, 1].min()
    corner = cloud.subset((cloud.xyz[:, 0] < x0 + size_m) & (cloud.xyz[:, 1] < y0 + size_m))
    labels = segment_trees(normalize(corner))
    path = folder / "corner.laz"
    write_las(path, corner, extra={"treeID": labels})
    return path, labels


def qgis_process(*args, timeout: int = 300):
    """Run headless qgis_process with this checkout's profile (scripts/setup.sh enables the plugin).

    Debian's /usr/bin/qgis_process wrapper fails on every command, so qgis_process.bin is preferred."""
    import subprocess

    binary = shutil.which("qgis_process.bin") or shutil.which("qgis_process")
    if binary is None:
        pytest.skip("qgis_process is not installed")
    profile = ROOT / ".qgis-profile"
    if not profile.exists():
        pytest.skip("run scripts/setup.sh first: it enables the plugin in .qgis-profile")
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen", QGIS_PLUGINPATH=str(ROOT / ".qgis-plugins"),
               QGIS_CUSTOM_CONFIG_PATH=str(profile))
    return subprocess.run([binary, *args], capture_output=True, text=True, env=env, timeout=timeout)


@pytest.fixture()
def sylva_provider(qgis_processing):
    """QGIS Processing initialised in this process, with Sylva's provider registered once."""
    from qgis.core import QgsApplication

    registry = QgsApplication.processingRegistry()
    provider = registry.providerById("sylva")
    if provider is None:
        from sylva.processing.provider import SylvaProvider

        provider = SylvaProvider()
        registry.addProvider(provider)
        _KEEP.append(provider)  # the registry does not own Python providers: keep it alive
    return provider


_KEEP = []


@pytest.fixture(scope="session", autouse=True)
def _headless():
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")


# Helper modules that sit beside the tests (e.g. badfiles.py) import as top-level modules, and the
# checkout itself must not be on sys.path: its `processing/` folder would hide QGIS's `processing`.
import sys  # noqa: E402

sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != ROOT]
sys.path.insert(0, str(Path(__file__).resolve().parent))
