#!/usr/bin/env bash
# Build the plugin ZIP a user installs with QGIS's "Plugins > Manage and Install Plugins > Install from ZIP":
#   dist/sylva-VERSION.zip holding one folder sylva/ with only the plugin's files (the git-tracked files of
#   the package, resources and LICENSE; no tests, benchmarks, scripts, tools, .venv or caches).
# Usage: bash scripts/package.sh [OUTPUT.zip]     (prints the path of the ZIP)
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
version="$(sed -n 's/^version=//p' "$root/metadata.txt")"
out="${1:-$root/dist/sylva-$version.zip}"
mkdir -p "$(dirname "$out")"
python3 - "$root" "$out" <<'PY'
import os, subprocess, sys, time, zipfile
from pathlib import Path

root, out = Path(sys.argv[1]), Path(sys.argv[2])
TOP = ("__init__.py", "metadata.txt", "LICENSE", "README.md", "cli.py", "pyproject.toml")
TREES = ("algorithms/", "core/", "plugin/", "processing/", "resources/")
try:
    files = subprocess.run(["git", "-C", str(root), "ls-files", "-z"], check=True, capture_output=True,
                           text=True).stdout.split("\0")
except (OSError, subprocess.CalledProcessError):   # not a git checkout: every file of the plugin's folders
    files = [str(p.relative_to(root)) for p in root.rglob("*") if p.is_file()]
keep = sorted(f for f in files if f and (f in TOP or f.startswith(TREES)) and "__pycache__" not in f
              and not f.endswith((".pyc", ".pyo")) and (root / f).is_file())
for required in ("__init__.py", "metadata.txt", "LICENSE"):
    if required not in keep:
        sys.exit(f"package.sh: {required} is missing from the plugin")
tmp = out.with_name(out.name + ".part")
stamp = time.localtime(int(os.environ.get("SOURCE_DATE_EPOCH", "315532800")))[:6]   # reproducible ZIP
with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
    for f in keep:
        info = zipfile.ZipInfo(f"sylva/{f}", date_time=stamp)
        info.external_attr = 0o644 << 16
        info.compress_type = zipfile.ZIP_DEFLATED
        z.writestr(info, (root / f).read_bytes())
os.replace(tmp, out)
print(out)
PY
