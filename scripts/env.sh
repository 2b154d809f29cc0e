# Source this file to run Sylva's qgis_process and tests headless (see ../QGIS_SETUP notes in README).
_sylva_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
export PATH="$_sylva_root/.venv/bin:$PATH"          # qgis_process runs the first python3 on PATH
export QT_QPA_PLATFORM=offscreen                     # no display needed
export QGIS_PLUGINPATH="$_sylva_root/.qgis-plugins"  # holds the link "sylva" -> this checkout
export QGIS_CUSTOM_CONFIG_PATH="$_sylva_root/.qgis-profile"
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp/runtime-$(id -u)}"
mkdir -p "$XDG_RUNTIME_DIR" && chmod 700 "$XDG_RUNTIME_DIR"
unset _sylva_root
