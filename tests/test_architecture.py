"""The layering ARCHITECTURE.md asks for: core/ (and the CLI side) never import qgis; imports run from a
higher layer to a lower one, without cycles, and take no private names from other modules."""
import ast
import collections
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


# --------------------------------------------------------------------------- the import graph

def _modules():
    """{dotted name: path} of Sylva's own modules (tests, benchmarks and scripts are not the package)."""
    mods = {}
    for folder in ("core", "algorithms", "plugin", "processing", "testing"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            name = "sylva." + ".".join(path.relative_to(ROOT).with_suffix("").parts)
            mods[name.removesuffix(".__init__")] = path
    for top in ("cli", "__init__"):
        mods["sylva" if top == "__init__" else f"sylva.{top}"] = ROOT / f"{top}.py"
    return mods


def _edges(mods):
    """(importer, imported module, name) for every import of a Sylva module, at any depth of the code."""
    for mod, path in mods.items():
        package = mod.split(".") if path.name == "__init__.py" else mod.split(".")[:-1]
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name.split(".")[0] == "sylva":
                        yield mod, alias.name, ""
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    base = ".".join(package[:len(package) - node.level + 1] + ([base] if base else []))
                if base.split(".")[0] != "sylva":
                    continue
                for alias in node.names:
                    sub = f"{base}.{alias.name}"
                    yield mod, sub if sub in mods else base, alias.name


#: Layers from the top down: a module may import its own layer's modules and any lower layer's,
#: never a higher one's.  core/ is QGIS-free and knows no front end; testing/ (simulators for tests
#: and benchmarks) stands on core/ and nothing at run time imports it.
LAYERS = (
    ("sylva", "sylva.plugin", "sylva.processing"),   # the QGIS plugin
    ("sylva.cli",),                                  # the command line
    ("sylva.algorithms",),                           # algorithm definitions shared by both front ends
    ("sylva.testing",),                              # simulated stands and scans
    ("sylva.core",),
)


def _layer(mod):
    best = None
    for i, prefixes in enumerate(LAYERS):
        for prefix in prefixes:
            if (mod == prefix or mod.startswith(prefix + ".")) and (best is None or len(prefix) > best[1]):
                best = (i, len(prefix))
    return best[0]


def test_imports_run_from_a_higher_layer_to_a_lower_one():
    mods = _modules()
    upward = sorted({f"{a} imports {b}" for a, b, _ in _edges(mods)
                     if b in mods and _layer(b) < _layer(a)})
    assert upward == []
    runtime = [m for m in mods if not m.startswith("sylva.testing")]
    assert not [f"{a} imports {b}" for a, b, _ in _edges(mods) if a in runtime and b.startswith("sylva.testing")]


def test_no_import_cycles():
    """No two modules import each other, however long the way round (Tarjan's strongly connected components)."""
    mods = _modules()
    graph = collections.defaultdict(set)
    for a, b, _ in _edges(mods):
        if b in mods and b != a:
            graph[a].add(b)
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(mods):
        if v not in index:
            visit(v)
    assert cycles == []


def test_no_private_names_cross_modules():
    mods = _modules()
    private = sorted(f"{a} takes {name} from {b}" for a, b, name in _edges(mods)
                     if name.startswith("_") and not name.startswith("__") and b != a)
    assert private == []
