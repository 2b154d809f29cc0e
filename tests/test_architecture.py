"""The layering ARCHITECTURE.md asks for: core/ (and the CLI side) never import qgis."""
import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _imports(path: Path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module


def test_no_module_under_core_imports_qgis():
    offenders = [
        f"{path.relative_to(ROOT)} imports {name}"
        for folder in ("core", "algorithms")
        for path in sorted((ROOT / folder).rglob("*.py"))
        for name in _imports(path)
        if name == "qgis" or name.startswith("qgis.") or name == "processing"
    ]
    assert (ROOT / "core" / "cloud.py").exists()
    assert offenders == []


def test_core_and_cli_import_with_qgis_unavailable():
    """Import every core module and the CLI in a Python where `import qgis` fails."""
    modules = sorted(
        "sylva." + ".".join(p.relative_to(ROOT).with_suffix("").parts).replace(".__init__", "")
        for folder in ("core", "algorithms")
        for p in (ROOT / folder).rglob("*.py")
    ) + ["sylva.cli", "sylva"]
    code = (
        "import sys, importlib\n"
        "sys.modules['qgis'] = None  # any `import qgis...` now raises ImportError\n"
        f"for m in {modules!r}:\n"
        "    importlib.import_module(m)\n"
        "print('ok', len(sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd="/")
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("ok")


def test_plugin_metadata():
    import configparser

    meta = configparser.ConfigParser()
    meta.read(ROOT / "metadata.txt")
    general = meta["general"]
    assert general["name"] == "Sylva"
    assert general["qgisMinimumVersion"] == "3.22"
    assert general["hasProcessingProvider"] == "yes"
    assert (ROOT / general["icon"]).exists()


def test_dependency_check_names_the_missing_package(monkeypatch):
    from sylva.plugin import deps

    monkeypatch.setattr(deps, "REQUIRED", deps.REQUIRED + (("surely_not_installed_pkg", "surely-not-installed"),))
    lacking = deps.missing()
    assert lacking == ["surely-not-installed"]
    hint = deps.install_hint(lacking)
    assert "surely-not-installed" in hint and "pip install" in hint
