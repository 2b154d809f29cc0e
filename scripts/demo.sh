#!/usr/bin/env bash
# Install everything (idempotent) and run Sylva's main job on the bundled sample tile
# through QGIS's own qgis_process; outputs land in ./demo-output/.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/setup.sh"
cd "$root"
# shellcheck source=scripts/env.sh
. scripts/env.sh
out="$root/demo-output"
sample="$root/resources/sample/sample.laz"
mkdir -p "$out"
run() { qgis_process.bin run "$@" 2>&1 | grep -v -e "setapi() is deprecated" -e "^$"; }
run sylva:canopyheightmodel --INPUT="$sample" --RESOLUTION=0.5 --PIT_FREE=true --OUTPUT="$out/chm.tif"
run sylva:treetops --INPUT="$sample" --WINDOW=0 --WINDOW_DIAMETER=3 --MIN_HEIGHT=2 --OUTPUT="$out/tree_tops.gpkg"
echo
echo "Outputs are in $out: chm.tif (canopy height model), tree_tops.gpkg (one point per tree)."
