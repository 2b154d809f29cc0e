"""Lightweight billboard trees: Zhou et al. 2013, "Automatic reconstruction of lightweight trees" §IV–§VI.

A tree becomes six textured quads with alpha (§IV): three around the axis of
the main trunk (which may lean) and three around a vertical crown axis,
60 degrees apart.  Trees without a single main trunk get the three crown
quads only (§VI-A, Fig. 5).

    bb = billboard_tree(xyz, Billboard(), rgb=colours, ground_z=0.0, tree_id=7)
    bb.vertices, bb.faces, bb.uvs, bb.texture        # metres, origin at the stem base, z up

Steps (one pure function each):

* :func:`shape_mask` — §V/§VI-A: the tree's points projected onto a
  vertical plane and rasterised (``pixel_m`` is the paper's scale factor
  ``s = (z_max - z_min) / img_height``: sizes come out in metres), holes
  closed and filled, noisy specks removed ("morphology operations to fill
  holes and remove noisy points").  The paper projects onto one camera
  image; Sylva projects onto ``planes`` vertical planes (0, 60, 120 degrees),
  one per quad, so that each quad shows its own silhouette.
* :func:`width_function` — §VI-A: ``f(y) = x_max - x_min`` of the edge pixels
  of each row (for a hole-free mask the outermost edge pixels are the
  mask's extremes).  :func:`first_change` finds the first non-zero
  ``∂f/∂y`` going up from the stem base, i.e. the first row where the width
  grows by more than ``width_jump_m`` over the mean width below it on two
  consecutive rows (the discrete, noise-proof reading of "non-zero").
* :func:`ransac_line` — §VI-A (RANSAC, Fischler & Bolles): the left and the
  right trunk edge lines in the approximate trunk area (seeded).  Their
  middle line is the trunk's rotation axis; the width is then re-measured
  between the edge points nearest the axis (Fig. 4c) and the trunk top found
  again: the accurate trunk box.  The crown box starts at the approximate
  trunk height (Fig. 4d); the crown axis is vertical, at the centre of the
  crown's extent (Fig. 4b).  :func:`fit_plane` does all this on one mask;
  :func:`shape_fit` combines the planes into a 3D trunk axis and a crown
  axis by least squares (a single trunk needs edge lines in at least two
  planes: "a tree with a single main trunk is determined only if it has two
  edge lines of the main trunk").
* Textures (§VI-B): point colours (LAS RGB, or sampled from an orthophoto
  :func:`sample_orthophoto` or a pinhole camera image :func:`sample_camera`,
  §V's ``P = K M``) splatted into the mask; :func:`gmm_clean` clusters the
  crown's pixels with a Gaussian mixture in HSV (scikit-learn, EM) and keeps
  the cluster nearest the mean HSV; :func:`complete_blocks` fills removed
  and unknown pixels block by block (Algorithm 1, cost Eq. 2 with the
  Bhattacharyya histogram distance Eq. 3 and the boundary SSD).  Without
  any colour a procedural foliage / bark texture is drawn
  (:func:`sylva.core.textures.foliage_texture`).
* :func:`quads` — the six (or three) quads, one texture atlas per tree
  (one material per tree in glTF).

Sylva departures from the paper, stated where they happen: several planes
instead of one image; the colours come from the points (the paper's image
is replaced by per-point colours); hue enters the GMM as a point on the HSV
cone (``s cos h, s sin h, v``) so that red hues do not wrap; the GMM only
cleans the crown (bark is a legitimately different colour); the boundary
SSD uses RGB in [0, 1] so that Eq. 2's two terms have comparable scales.

Sylva, not in the paper (speed; at most 0.1 s a tree for 100k points, the
paper's own figure being 0.37–1.32 s): the point spacing that sets the
closing radius is bounded on a subset of the points first (:func:`.shape._close_px`);
the closing uses exact discs without distance transforms (:func:`.shape._disc_dilate`;
the disc stamped on each point when there are few); holes and specks are
found in the mask's bounding box; the plane's pixel rows are computed once
for every plane; the GMM's EM runs as scikit-learn's algorithm in a few
vectorised lines (:func:`.texture._gmm_diag`); block completion works in the mask's
bounding box and updates its neighbour counts incrementally; no BLAS call
touches all the points (its threads spin on a busy machine).  Each gives the
same masks, axes, boxes and opaque texels as the straightforward version.

Modules: :mod:`.shape` (§V/§VI-A masks and plane fit), :mod:`.colour` (§V point colours, orthophoto
and camera), :mod:`.texture` (§VI-B GMM cleaning and block completion), :mod:`.tree` (the parameters,
:func:`billboard_tree` and the atlas packing); the public names are re-exported here.
"""
from __future__ import annotations

from .colour import (Orthophoto, PinholeCamera, point_rgb, read_camera, read_orthophoto, sample_camera,
                     sample_orthophoto)
from .shape import PlaneFit, crown_box, first_change, fit_plane, ransac_line, shape_fit, shape_mask, width_function
from .texture import bhattacharyya, complete_blocks, gmm_clean
from .tree import Billboard, BillboardMesh, billboard_tree, opaque_points

__all__ = ["Billboard", "BillboardMesh", "PlaneFit", "Orthophoto", "PinholeCamera", "billboard_tree",
           "shape_mask", "width_function", "first_change", "ransac_line", "fit_plane", "shape_fit",
           "point_rgb", "read_orthophoto", "sample_orthophoto", "read_camera", "sample_camera", "gmm_clean",
           "complete_blocks", "bhattacharyya", "opaque_points"]
