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
# The main job: tiles -> trees -> 3D models (one tile here; give a folder or a .vpc for many).
run sylva:pipeline --INPUT="$sample" --OUTPUT_FOLDER="$out/forest"
run sylva:canopyheightmodel --INPUT="$sample" --RESOLUTION_M=0.5 --PIT_FREE=true --OUTPUT="$out/chm.tif"
run sylva:exportmodels --INPUT="$out/forest/models/sample.glb" --CITYGML="$out/trees.gml" --OBJ="$out/trees.obj"
echo
echo "Outputs are in $out:"
echo "  forest/forest.gpkg   trees table, tree_tops, crowns, crown_points, stem_points, skeletons, models_3d, crowns_3d"
echo "  forest/tiles/        the tile with a treeID per point (normalised cut, Hu et al. 2017)"
echo "  forest/models/       a georeferenced GLB per tile and a 3D Tiles tileset (Cesium, QGIS >= 3.34)"
echo "  forest/report.txt    what was done: tiles, trees, failures, time"
echo "  chm.tif              pit-free canopy height model (m above ground)"
echo "  trees.gml, trees.obj the same models as CityGML 2.0 and OBJ (for Blender)"
