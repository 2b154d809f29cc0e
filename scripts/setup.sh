#!/usr/bin/env bash
# Install everything Sylva needs on Debian 12, idempotently:
#   - QGIS 3.22 and its Python bindings from Debian's packages (apt),
#   - a virtual environment .venv on Debian's python3 that also sees the QGIS bindings,
#     with Sylva and its Python dependencies from PyPI (pip install -e .[test]),
#   - a QGIS profile in .qgis-profile with the plugin enabled, for qgis_process.
# With --viewers (what scripts/test.sh asks for) it also installs the real 3D viewers the export
# tests drive: Chromium and Xvfb (Debian; Xvfb for QGIS's own 3D renderer), Node.js packages in tools/viewers (npm: glTF validator, loaders.gl,
# CesiumJS) and, when Maven is present, the CityGML schemas (citygml4j from Maven Central).
# A second run only checks and returns in a few seconds.
set -euo pipefail
viewers=0
[ "${1:-}" = "--viewers" ] && viewers=1
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"

sudo_cmd=""
if [ "$(id -u)" -ne 0 ]; then sudo_cmd="sudo"; fi

debs="qgis python3-qgis qgis-providers python3-gdal python3-venv"
if [ "$viewers" = 1 ]; then
    debs="$debs chromium xvfb"
    command -v node >/dev/null 2>&1 || debs="$debs nodejs npm"
fi
want_n=$(echo $debs | wc -w)
if ! dpkg-query -W -f='${Status}\n' $debs 2>/dev/null | grep -c "install ok installed" | grep -qx "$want_n"; then
    echo "setup: installing from Debian's packages: $debs (a minute or two)..."
    $sudo_cmd apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends $debs >/dev/null
fi

stamp=".venv/.sylva-installed"
want="$(sha256sum pyproject.toml | cut -d' ' -f1)"
if [ ! -x .venv/bin/python ] || [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
    echo "setup: creating .venv with Sylva's Python dependencies..."
    /usr/bin/python3 -m venv --system-site-packages .venv
    .venv/bin/python -m pip install -q --disable-pip-version-check -e '.[test]'
    # Debian's pyproj looks for its data under sys.prefix/share/proj: point it at Debian's.
    mkdir -p .venv/share && ln -sfn /usr/share/proj .venv/share/proj
    echo "$want" > "$stamp"
fi

# qgis_process finds plugins in QGIS_PLUGINPATH by folder name: link this checkout as "sylva".
mkdir -p .qgis-plugins
ln -sfn "$root" .qgis-plugins/sylva
# shellcheck source=scripts/env.sh
. scripts/env.sh
if ! grep -qs "^sylva=true" "$QGIS_CUSTOM_CONFIG_PATH/profiles/default/QGIS/QGIS3.ini"; then
    qgis_process.bin plugins enable sylva >/dev/null 2>&1 || true
    grep -qs "^sylva=true" "$QGIS_CUSTOM_CONFIG_PATH/profiles/default/QGIS/QGIS3.ini" \
        || { echo "setup: could not enable the sylva plugin in $QGIS_CUSTOM_CONFIG_PATH" >&2; exit 1; }
fi

# Compile and cache the numba kernels now, so that the first run is not a minute of silence
# (plugin/warmup.py; a stamp makes a second set-up skip it in a second).
# Imported through .qgis-plugins/sylva, the path QGIS loads the plugin from (numba keys a NUMBA_CACHE_DIR
# cache by the source's path; the default cache beside the sources serves the CLI as well).
PYTHONPATH="$root/.qgis-plugins${PYTHONPATH:+:$PYTHONPATH}" .venv/bin/python -m sylva.plugin.warmup --if-needed
if [ -n "${NUMBA_CACHE_DIR:-}" ]; then   # that cache is keyed by path: warm the checkout's path (the CLI's) too
    .venv/bin/python -m sylva.plugin.warmup --if-needed
fi

if [ "$viewers" = 1 ]; then
    lock="tools/viewers/package-lock.json"
    stamp_v="tools/viewers/node_modules/.sylva-installed"
    if [ "$(cat "$stamp_v" 2>/dev/null)" != "$(sha256sum "$lock" | cut -d' ' -f1)" ]; then
        echo "setup: installing the viewer checks' npm packages (tools/viewers)..."
        (cd tools/viewers && npm ci --no-audit --no-fund --loglevel=error >/dev/null)
        sha256sum "$lock" | cut -d' ' -f1 > "$stamp_v"
    fi
    if command -v mvn >/dev/null 2>&1 && ! ls ~/.m2/repository/org/citygml4j/citygml4j-xml/3.0.0/*.jar >/dev/null 2>&1; then
        echo "setup: fetching the CityGML schemas (citygml4j-xml from Maven Central)..."
        mvn -q dependency:get -Dartifact=org.citygml4j:citygml4j-xml:3.0.0 -Dtransitive=false >/dev/null \
            || echo "setup: could not fetch citygml4j; the CityGML schema tests will skip" >&2
    fi
fi
