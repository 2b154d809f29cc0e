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
run sylva:canopyheightmodel --INPUT="$sample" --RESOLUTION_M=0.5 --PIT_FREE=true --OUTPUT="$out/chm.tif"
run sylva:treetops --INPUT="$sample" --WINDOW=1 --MIN_HEIGHT_M=2 --OUTPUT="$out/tree_tops.gpkg"
run sylva:segmenttrees --INPUT="$sample" --METHOD=0 --OUTPUT="$out/segmented.laz" \
    --TREE_TOPS="$out/seg_tree_tops.gpkg" --CROWNS="$out/crowns.gpkg" --CROWN_POINTS="$out/crown_points.gpkg" \
    --STEM_POINTS="$out/stem_points.gpkg" --TREES="$out/trees.gpkg"
run sylva:reconstructtrees --INPUT="$out/segmented.laz" --METHOD=0 --LOD=0 --MODELS="$out/trees.glb" \
    --SKELETONS="$out/skeletons.gpkg" --TREES="$out/trees_models.gpkg"
echo
echo "Outputs are in $out:"
echo "  chm.tif            canopy height model (m above ground)"
echo "  tree_tops.gpkg     local-maximum tree tops"
echo "  segmented.laz      the sample tile with a treeID per point (normalised cut, Hu et al. 2017)"
echo "  crowns.gpkg, crown_points.gpkg, stem_points.gpkg, seg_tree_tops.gpkg, trees.gpkg"
echo "  trees.glb          a georeferenced 3D model of every tree (Hu et al. 2017 / Guo et al. 2018)"
echo "  skeletons.gpkg     branch skeletons (radius as M), trees_models.gpkg: the trees table with DBH, volume..."
