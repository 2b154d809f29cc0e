"""Normalised-cut tree segmentation on a voxel graph (Hu et al. 2017, §4.1).

Hu, Li, Zhang, Xie, Wang, Guo, Xiao, Su (2017), "Efficient tree modeling from
airborne LiDAR point clouds", Computers & Graphics 67, §4.1 and §6.1.

Steps
-----
1. **Voxels.** Points at least ``min_height_m`` above ground are binned into
   cubes of pitch ``voxel_m`` (the paper's d_s; 0.7 m for 36 k points, 0.9 m
   for 3.7 M points, §6.1) in the local metric frame, z = height above ground
   (so huge UTM coordinates and sloping terrain do not matter).  A voxel's
   features are the mean local (x, y, height), the mean intensity and the
   mean RGB colour when the cloud has them.
2. **Graph (Eq. 2).** The paper writes ``w_ij = e^{-H} e^{-V} e^{-I} e^{-C}``
   without scales; we use

       w_ij = exp(-H/σ_h) · exp(-V/σ_v) · exp(-I/σ_i) · exp(-C/σ_c)

   with H, V the horizontal and vertical distances of the voxel means
   (metres), I the absolute difference of the voxels' mean natural-log
   intensities (a ratio of intensities: free of the sensor's units and of any
   statistic of the tile, so tiling does not change the weights; the
   inter-quartile range of ln I is about 1 on lidR's MixedConifer and on the
   synthetic stands), and C the Euclidean distance of mean colours scaled to
   [0, 1].  The exponent stays linear in the distance
   as Eq. 2 writes it (not squared as in Shi & Malik's Gaussian kernel); the
   σ's carry the units the paper leaves implicit (``sigma_h_m``,
   ``sigma_v_m``, ``sigma_intensity``, ``sigma_colour``).  w_ij = 0 beyond
   r^xz = ``radius_m``; to keep the graph sparse the cylinder of Eq. 2 is
   cut to the inscribed ellipsoid of half height ``height_m``
   (``cKDTree.query_pairs`` on z-scaled coordinates); steep conifer apices
   stay connected, far-apart layers are not joined.  No dense
   matrix is ever built.
3. **Tops and start.** Unless given, tree tops are the local maxima of
   :func:`sylva.core.tops.find_tree_tops` (fixed window ``top_window_m``,
   small on purpose: surplus tops are merged in step 4) searched among the
   highest point of each ``TOP_CELL_M`` column only (every top is such a
   point; a canopy-surface thinning that makes the search several times
   faster).  Such a point with no other crown point within ``ISOLATION_M``
   (2 m, 3-D) is noise, unless one lies below it as steeply as a conifer's
   apex drops (``apex_slope``) within 2 x ``apex_slope`` pulse spacings
   (1 / sqrt of the canopy density around it): at 2 points/m2 the highest
   return of a crown rising 3-7 m per metre stands 2-5 m above the next, and
   the fixed 2 m test threw such tips away, leaving the tree's top on its
   flank, metres lower and off its stem (:meth:`NormalizedCut._isolated`;
   a stray return beside a crown or over the ground is still noise).  With
   the attachment of step 5 that judges a lone small tree with the crown
   points under it (Sylva, not in Hu et al.): ``benchmarks/segmentation.py``
   seed 0, conifer open / medium / dense at 2 points/m2 0.963 / 0.882 /
   0.761 -> 0.979 / 0.914 / 0.769, mixed medium / dense at 2 0.743 / 0.634
   -> 0.771 / 0.656, tall open / medium / dense at 2 0.818 / 0.727 / 0.670
   -> 0.856 / 0.743 / 0.690, the 12 stands at 2 points/m2 0.778 -> 0.794;
   at 5 points/m2 and more the most a stand loses is 0.009 (tall dense at
   5); held out, seed 1: +0.17 summed, at 2 points/m2 0.758 -> 0.774 (tall
   medium at 5 -0.012); 30 degree slopes: conifer medium / dense at 2
   0.837 / 0.716 -> 0.886 / 0.749; MixedConifer 279 -> 280 trees,
   autzen_trim 277 -> 279; with the lower-crown rule of the understory
   below too, on ``benchmarks/analytic_stands.py`` (a generator written
   apart from the suite, seeds 0-2), conical conifers at 2 / 5 points/m2
   0.610 / 0.886 -> 0.792 / 0.959 and a plantation 0.822 / 0.957 -> 0.930
   / 0.990, against 0.837 / 0.971 and 0.932 / 0.995 for the true trees
   themselves.  Sylva
   additions (not in Hu et al.), measured with
   ``benchmarks/segmentation.py``: at low point density the window is
   widened until it holds ``top_window_points`` canopy points (first returns
   per m² of canopy, so a local maximum is not a sampling accident: 2.7 m on
   lidR's MixedConifer at 4.3 points/m²) and at least ``top_window_crown``
   (0.4) x the crown width of Popescu & Wynne's (2004) allometry at the
   point's height (their variable window, narrowed: a bump on a broad crown
   is not a top, a neighbour is rarely nearer).  Where the canopy is closed
   (:func:`canopy_cover` at least ``CLOSED_COVER``, 0.75, within
   ``COVER_REACH`` crown radii) the neighbours have narrowed the crowns and a
   neighbour is nearer: the maxima of a window whose crown share shrinks to
   ``closed_window`` (0.4) x ``top_window_crown``, 0.16 x the crown width,
   are tops too (not in the "open-grown" preset).  Detection F1 without and
   with it (``benchmarks/segmentation.py --sizes 0``, seed 0): tall stands
   (30-60 m) at 5 points/m2 and more 0.787 -> 0.818 (dense 0.602-0.661 ->
   0.695-0.724), dense broadleaves at 20 points/m2 0.777 -> 0.789; dense
   mixed stands lose 0.004-0.020, the conifer, broadleaf and mixed stands
   together 0.890 -> 0.889; a held-out tall dense stand (seed 3) 0.601 ->
   0.732.  A window narrowed by canopy points too (10 instead of 25 in a
   closed canopy) gained more on the sparse dense stands but cut
   MixedConifer.laz into 313 trees instead of 271; judging the narrower
   window's tops in elevation too (against the downhill shift on slopes)
   took the gain away on sloping tall stands: neither is in.  And the
   steep-apex rule (:class:`sylva.core.tops.SteepApex`: ``apex_window_m``,
   ``apex_slope``, ``apex_sectors``) adds the tips of narrow conifers that a taller
   neighbour overtops within the window, the main loss of recall in dense
   stands.  Apexes of a lower crown layer are tops too (``lower_layer``,
   :func:`~.layers.lower_layer_apexes`): a crown point under the edge of a
   higher crown with an empty band above it and a crown below it, where the
   canopy is closed and the scan dense, as Hamraz et al. (2017) find the
   lower layers below a gap in the vertical profile: dense broadleaves at
   20 points/m2 0.792 -> 0.820, dense conifers 0.910 -> 0.917, dense mixed
   stands 0.810 -> 0.817 (figures and what it costs in that module).
   Every voxel gets the tree top nearest to it along the graph
   (multi-source Dijkstra); a step costs the Eq. 2 dissimilarity -log w_ij
   plus ``climb`` x the height it gains, so a region runs down its own crown
   and stops at the crease where the neighbouring crown rises again.  Voxels
   of components without a top are not reached (isolated noise), unless the
   component is a crown of its own: the tops are maxima of the canopy
   surface, so a suppressed tree under a taller crown (more than
   ``height_m`` below it) has none; a component no top reaches that holds at
   least ``understory_points`` (40) crown points and spans
   ``understory_extent_m`` (2.5 m) with its highest point near its centre
   (``APEX_CENTRED``: a lower piece of a taller tree's crown that a sparse
   scan cut off is not centred on its highest point) gets that point as a
   top (Sylva, not in Hu et al.; understory trees segmented apart from the
   overstory as in Hamraz et al. 2017, ISPRS J. Photogramm. 130).  Measured
   with ``benchmarks/segmentation.py --variants '[{}, {"understory_points":
   0}]'``: dense stands' F1 rises 0.750 -> 0.769 (broadleaf), 0.749 -> 0.760
   (mixed), 0.877 -> 0.883 (conifer), and no stand of the panel loses;
   MixedConifer, whose lidR reference has no understory, gets 3 more trees
   (283 -> 286).  But a topless component centred within
   ``LOWER_CROWN_REACH`` (0.6) crown radii (the forest allometry's) of a
   taller tree's apex (a top higher than every other within its crown
   radius) is that tree's lower crown, not a tree
   (:func:`.graph.topless_crowns`): where a sparse scan's returns lie
   farther apart up a steep conifer's flank than ``height_m``, the skirt
   around its stem is a component of its own, as wide as a tree, with its
   highest point near its centre; a suppressed tree stands beside its
   dominant, about a crown radius from its apex (Sylva, not in Hu et al.).
   ``benchmarks/analytic_stands.py`` at 5 points/m2, seeds 0 / 1 / 2:
   conical conifers 0.918 / 0.896 / 0.866 -> 1.000 / 0.945 / 0.933 (52
   trees found for 45 -> 45), a plantation 0.955 / 0.962 / 0.955 -> 1.000
   / 1.000 / 0.969; ``benchmarks/segmentation.py`` seed 0: tall open at 5
   points/m2 0.906 -> 0.939,
   conifer medium at 5 0.968 -> 0.976, the 48 forest stands +0.074 summed,
   the most a stand loses 0.004 (mixed open at 20 and 50); seed 1 +0.096
   summed (tall open at 20 0.891 -> 0.914; mixed open at 50 -0.008); 30
   degree slopes +0.009; MixedConifer, autzen_trim and the sample
   unchanged.  The "open-grown" preset turns it off (``lower_crown_reach``
   0): its broad crowns are no spires, and its dense parkland at 2-50
   points/m2 lost 0.008 to 0.010 with it.
4. **Cuts (Eq. 1).** The problem is split into independent two-tree
   sub-problems.  The NCut of the start boundary of every pair of touching
   regions is computed at once (edge sums); pairs whose start boundary
   already costs less than ``SETTLED_NCUT`` are clearly separate crowns and
   are left as they are.  For the others, the generalised eigenproblem
   (D − W) x = λ D x of their union (normalised Laplacian, LOBPCG from the
   current boundary, ``scipy.linalg.eigh`` for tiny problems) gives the
   Fiedler vector, and Shi & Malik's threshold search finds the split with
   the smallest NCut(A, B) that keeps each top on its own side.  The new
   boundary replaces the old one only if its NCut is lower.  The best cut of
   a pair (the lower of the Fiedler split and the start boundary) says
   whether the two regions are one tree with two local maxima: the lower top
   is merged into the higher one (which keeps its id) when it costs more than
   ``always_merge_ncut``, or more than ``merge_ncut`` while the crowns dip
   between the two tops by less than ``merge_dip`` x the lower top's height
   (the dip is measured to the saddle, the highest voxel edge across their
   boundary).  Hu §4.1 lets the cut, not a root point per tree, decide the
   number of trees; the NCut value alone does not separate a surplus top on
   one crown (its cut is expensive, but so is the cut between two trees of
   a dense, interlocking canopy), the saddle depth does (a Sylva addition,
   not in Hu et al.): measured on the
   synthetic stands, the dip of a surplus top is 0.6–3.4 % of the lower top
   (10th–90th percentile), that of two trees 3–33 %.  A lower top that
   qualifies for merging with several neighbours joins only the one across
   the highest saddle (smallest dip), so a surplus top lying between two
   trees does not chain them into one.  Each sub-problem holds
   two crowns, so time and memory grow linearly with the tile.
   **Crown-reach merge** (issue 16; Sylva, not in Hu et al.): the cut
   cannot tell a leaf clump, a second leader or a flat crown's bump from a
   tree, as its crown is wide and the cut between its halves cheap.  A pair
   of touching regions (settled or not) is one tree when the lower top lies
   within ``merge_reach`` x the crown radius the higher top's height implies
   (half the crown width of Popescu & Wynne 2004, CW = 2.51503 + 0.00901 h²,
   at most 12 m, :func:`crown_radius_m`) and rises less than ``merge_prominence`` x its
   height above their saddle (the prominence of the EBImage/lidR watershed's
   ``tol``, relative to height).  Measured on 2,530 pairs of the extended
   suite (``sylva/testing/crowns.py``) and testing/synth's dense conifers: pairs
   of one tree lie at 0.06-0.17 x the higher top's height (10th-90th
   percentile), pairs of two trees at 0.13-0.33; reach 0.7 and prominence 0.15
   merge 1,599 of 2,022 same-tree pairs and 123 of 508 two-tree pairs (the
   old rule alone: 1,359 and 103); a reach of 1.0 merges more on broadleaves
   but joins dense conifers (net gain there 55 -> 16 pairs).  Two tops of
   nearly one height (differing by less than ``merge_plateau`` x the higher)
   whose saddle dips less than half ``merge_prominence`` are the plateau of a
   flat-topped crown up to ``PLATEAU_REACH`` (1.3) x the crown radius: net
   gain 1,476 -> 1,634 pairs, dense conifers 55 -> 50.  The graph does not
   always join the leaders of one crown: a sparse scan, or a clumped crown's
   gaps between its leaders' foliage (wider than ``radius_m``), leave their
   regions apart with no saddle to measure.  Two such tops of nearly one
   height (``merge_plateau``) within ``PLATEAU_REACH`` crown radii are one
   crown too when both are rounded (not a steep apex: two conifer leaders
   this close are two trees) and the canopy around the higher is not closed
   (:func:`canopy_cover` below ``CLOSED_COVER``, 0.75: in a closed
   canopy two crowns of one height do stand this close; on MixedConifer,
   around whose tops the canopy covers 0.8, lidR holds 6 of the 7 pairs
   the rule would join without this test in two trees, and both of the 2
   it joins with it) (:func:`.cut.unjoined_plateaus`; Sylva, not in Hu et
   al.).  Of such merges on 14 stands of the suite (open to dense, 2 to 20
   points/m2), 144 joined the tops of one tree and 3 of two;
   detection F1 (``benchmarks/segmentation.py``, seed 0): open broadleaves
   at 2 / 5 / 20 / 50 points/m2 0.799 / 0.821 / 0.852 / 0.866 -> 0.889 /
   0.848 / 0.881 / 0.882, medium broadleaves at 2 0.795 -> 0.828, open mixed
   stands at 2 / 5 / 20 0.712 / 0.792 / 0.824 -> 0.777 / 0.828 / 0.855,
   conifers and dense stands within 0.002; mean 0.862 -> 0.869 at 5 points/m2
   and more, 0.749 -> 0.773 at 2; MixedConifer 284 -> 282 trees.  With no
   saddle to judge such a pair by, the higher crown is judged as one no wider
   than ``CLOSED_CROWN_WIDTH_M`` (9 m), as in a closed canopy: the tall
   stands' 30-60 m trees had Popescu & Wynne's extrapolated 12 m crown, and
   10 of the 15 pairs the rule joined in the tall medium stand at 2
   points/m2 were two trees.  ``benchmarks/segmentation.py`` (seed 0): tall
   open at 2 / 20 0.748 / 0.939 -> 0.763 / 0.951, tall medium at 2 / 5 / 20
   / 50 0.676 / 0.787 / 0.848 / 0.853 -> 0.680 / 0.817 / 0.862 / 0.859, the
   tall stands' mean at 5 points/m2 and more 0.841 -> 0.848, dense conifers
   (up to 34 m) at 20 0.926 -> 0.929; on a 30 degree
   slope tall medium at 5 0.741 -> 0.769; held out (seed 1) tall medium at
   2 0.637 -> 0.651; the most a stand loses is 0.004 (parkland dense at 50,
   forest defaults); the "open-grown" preset's parkland dense at 5 0.782 ->
   0.797; the broadleaf and mixed stands (8-30 m), the sample and
   MixedConifer unchanged.  **Open-grown crowns**
   (Sylva, not in Hu et al.): Popescu & Wynne's allometry describes trees
   grown in stands, and a tree grown in the open has a wider crown of the
   same height (the open-grown crown width of Krajicek, Brinkman & Gingrich
   1961's crown competition factor).  Where the canopy around the higher top
   is open (:func:`canopy_cover`: under ``open_cover`` (0.6) of the
   1 m columns within 2 crown radii, at most 10 m, reach half its height;
   about 0.55 in the open stands of the suite, 0.84 in the dense ones) the
   merge reaches ``open_reach`` (0.9) crown radii, for a rounded lower top
   only: a steep apex (:func:`sylva.core.tops.steep_tops`, the
   :class:`~sylva.core.tops.SteepApex` test) is a conifer's one leader, not
   a bump.  Measured with ``benchmarks/segmentation.py`` (all 36 stands):
   open broadleaf 20 points/m² 0.834 -> 0.864, mixed open 0.78-0.80 ->
   0.79-0.81, dense stands within 0.002; conifer medium 20 0.985 -> 0.981,
   the pipeline's conifer medium 5 0.964 -> 0.959 and the shipped sample
   0.969 -> 0.966 lose.  **Closed canopies** (Sylva, not in Hu et al.): where
   the canopy around the higher top is closed (``CLOSED_COVER``), the
   neighbours bound a crown, not its height, and the merge reaches at most
   the radius of a crown ``CLOSED_CROWN_WIDTH_M`` (9 m) wide instead of
   Popescu & Wynne's up to 12 m: the tall stands' 30-60 m trees at 400
   stems/ha have crowns about 5 m wide, and the 12 m crown joined
   neighbours 4 m apart (given the true apexes as tops, tall dense at 20
   points/m2 scores F1 0.800 with every merge on, 0.943 with none).
   Measured with ``benchmarks/segmentation.py`` (60 stands, seed 0): tall
   dense at 5 / 20 / 50 points/m2 0.715 / 0.720 / 0.693 -> 0.731 / 0.768 /
   0.738, tall medium at 20 0.827 -> 0.837, conifer dense at 20 0.906 ->
   0.910; the most a stand loses is 0.004 (tall open at 50); parkland (both
   presets), the shipped sample and MixedConifer unchanged; held out (seed
   1): tall dense at 5 / 20 0.629 / 0.663 -> 0.645 / 0.698, the others of
   the panel within 0.004.  The plateau rule judged again on the finished
   crowns (step 5) is bounded the same way: tall dense at 5 / 20 / 50 ->
   0.740 / 0.777 / 0.751, tall medium at 20 -> 0.844, mixed dense at 20
   0.811 -> 0.810, no other stand changes (seed 1: tall dense at 20 0.698
   -> 0.700).  And the cut's merges judge the higher crown there as one no
   taller than ``CLOSED_HEIGHT_M`` (26.8 m, whose crown is 9 m wide) in the
   prominence and levelness of the lower top too (15 % of a 45 m tree is a
   6.8 m saddle, deeper than the saddle of two 5 m wide crowns): tall dense
   at 2 / 5 / 20 / 50 -> 0.624 / 0.743 / 0.786 / 0.768, tall medium within
   0.003, no other stand of the 48 forest stands changes (seed 1: tall
   dense at 5 / 20 0.645 / 0.700 -> 0.655 / 0.709, tall medium at 20
   -0.002).  A 7 m bound gained no more in tall stands and
   lost 0.007 on dense mixed ones; the 9 m bound on every use of the crown
   radius (top window, clean-up), not only where the canopy is closed,
   gained more in tall stands (dense at 20: 0.790) but lost in tall open
   ones (0.911 -> 0.892) and on the shipped sample (0.985 -> 0.975).
   **Crown classes** (Sylva, not in Hu et al.): a lower top under
   ``merge_height_ratio`` (0.8) x the higher top's height that rises above
   their saddle and stands beyond ``UNDER_CROWN`` (0.5) of the higher
   crown's allometric radius is merged only by a cut dearer than
   ``always_merge_ncut`` (Eq. 1 alone), by no other rule (a "top" below the
   saddle, or under the higher crown, where a tree of its own would be
   hidden, is a bump of that crown's flank and is merged as before).
   Surplus tops of one crown (second leaders, leaf clumps, a flat crown's
   bumps) stand near its apex height, while a top a fifth lower is the apex
   of a tree of a lower crown class (Kraft's 1884 dominant / co-dominant /
   intermediate / suppressed classes: an intermediate tree's crown reaches
   into the gaps of the dominant canopy).  Measured on the merges of 15
   stands of the suite and MixedConifer (each merge right when both tops'
   voxels belong to one true tree): the rules' right merges join tops at
   0.93-0.99 of the higher top (median per stand), their wrong merges in
   the dense stands at 0.69-0.85; the cap blocks 85 wrong merges and 10
   right ones (dense conifers at 20 / 50 points/m2: 19 / 23 wrong, 0 right;
   MixedConifer, lidR's trees as the reference: 1 wrong, 3 right).  With
   ``benchmarks/segmentation.py`` (all 36 stands, seed 0): dense conifers
   at 5 / 20 / 50 points/m2 0.864 / 0.882 / 0.866 -> 0.871 / 0.910 / 0.891,
   dense broadleaves at 20 0.761 -> 0.772, the shipped sample 0.966 ->
   0.973; open and medium mixed stands and open broadleaves at 50 lose up
   to 0.009; mean 0.859 -> 0.862; MixedConifer unchanged (284 trees).  On
   the ``--variants`` panel at seed 1: dense conifers 0.869 -> 0.885, the
   others within 0.006.
5. **Clean-up and points.** Nothing of a tree lies above its top; voxels cut
   off from their top go to the neighbour they are most strongly joined to
   (a tree's tops are its own and every top merged into it: a clumped
   open-grown crown whose gaps the graph does not cross keeps the pieces
   around its merged tops; held-out parkland, seed 5, open at 2 points/m2,
   "open-grown" preset: crown points without a tree 7 % -> 0.1 %, the worst
   tree's share 100 % -> 0 %; parkland seed 0 with the preset: point accuracy
   mean 0.794 -> 0.811, F1 mean 0.764 -> 0.770); crown pieces a sparse
   scan left unconnected join the nearest tree within ``attach_m``.  Points
   take their voxel's label; a point farther from its tree's top than
   ``crown_reach`` x that tree's allometric crown radius goes to a tree
   whose top is within reach (Dalponte & Coomes's maximum crown
   size, scaled by height; a stray carried across a neighbour's crown by the
   graph; MixedConifer crown IoU with lidR 0.489 -> 0.587); a tree whose
   apex lies off the centre of its crown (farther than ``OFF_CENTRE`` (0.8)
   x the RMS radius of its points above ``CROWN_TOP_SHARE`` (0.6) of its
   height from their centroid) and is not a steep apex is a piece of a wider
   crown (a leader or leaf clump at its rim, cut off with the rim around it)
   and joins the tree at least ``LEAN_HEIGHT_RATIO`` (0.85) as high whose top
   lies the way it leans, within ``LEAN_REACH`` (2) of that tree's crown radii
   (:func:`.cleanup.merge_off_centre`; Sylva, not in Hu et al.: 0-4 % of the
   trees that match a true tree are off-centre, 30-53 % of the split pieces;
   ``benchmarks/segmentation.py`` seed 0: open broadleaves at 2 / 5 / 20 / 50
   points/m2 0.889 / 0.848 / 0.881 / 0.882 -> 0.896 / 0.865 / 0.901 / 0.892,
   open mixed at 5 / 20 0.828 / 0.855 -> 0.846 / 0.867, medium mixed at 5 /
   20 0.813 / 0.855 -> 0.822 / 0.863, no stand loses more than 0.003; mean
   0.869 -> 0.875 at 5 points/m2 and more; MixedConifer 282 -> 275 trees,
   IoU 0.584 -> 0.588); a round, one-domed canopy island too wide for a
   forest crown (0.3-0.65 x its height) is one open-grown tree, its pieces
   merged into its highest (:func:`.islands.merge_round_islands`; Sylva, not
   in Hu et al.: on the suite's open parkland stands, seed 0, 19 trees at
   2 / 5 / 20 / 50 points/m2, 103 / 144 / 154 / 158 -> 73 / 91 / 111 / 113
   segments, F1 0.311 / 0.233 / 0.220 / 0.215 -> 0.413 / 0.327 / 0.277 /
   0.288; no forest stand changes);
   last, a tree of
   fewer than ``min_tree_points`` points (or, where the scan is sparse, the
   first returns of ``MIN_TREE_AREA_M2`` of canopy around its top) is merged
   into the tree within crown reach whose top is nearest, or is no tree
   (never reported as one), unless its top is higher than every tree within
   reach: then it is the apex of the tallest crown around, a tall spire a
   sparse scan left apart from its own lower crown (returns farther apart
   than ``height_m`` up the spire), and it stays, flagged ``quality``
   "sparse" in the trees table (before, its points, the highest of the
   stand, went to no tree; ``benchmarks/segmentation.py``, seed 0: tall open
   / medium / dense at 2 points/m2 0.763 / 0.680 / 0.622 -> 0.800 / 0.696 /
   0.642, tall dense at 5 0.746 -> 0.763, the tall stands' mean at 5
   points/m2 and more 0.848 -> 0.850; tall open at 5 -0.007 and mixed open
   at 5 -0.006 lose most; held out, seed 1: tall medium at 2 0.651 ->
   0.702, no tall or mixed stand loses; MixedConifer 271 -> 272 trees, IoU
   0.591 -> 0.589, one tree of 19 points).  So does a small tree whose top
   is a steep apex (the ``apex_slope`` test of step 3) farther than
   ``open_reach`` (0.9) crown radii from every tree as high (a neighbour
   judged at most ``CLOSED_HEIGHT_M`` high where the canopy is closed): the
   narrow top of a conifer outside its neighbours' crowns, whose lower crown
   the graph of a sparse scan gave to them, not a leaf clump of one (seed 0:
   conifer medium / dense at 2 points/m2 0.857 / 0.748 -> 0.880 / 0.757,
   tall open / medium / dense at 2 0.794 / 0.703 / 0.642 -> 0.815 / 0.723 /
   0.673, tall dense at 5 0.769 -> 0.782, no stand loses; held out, seed 1:
   +0.004 to +0.047 on 14 stands, none lower; 30 degree slopes +0.004 to
   +0.017 on 8 stands, none lower; parkland dense at 2 with the forest
   defaults -0.005; MixedConifer 272 -> 279 trees, 1.8 % under 20 points,
   IoU unchanged; autzen_trim 270 -> 277); points below
   ``min_height_m`` take the label of the crown right above them (stems),
   see :mod:`sylva.core.segment`; crown points still of no tree (graph
   pieces no top reached, farther than ``attach_m`` from every tree and under
   no crown: a clumped crown's leaf clumps, a sparse scan's loose returns) go
   to the tree within crown reach whose top is nearest, as the strays above
   (Sylva, not in Hu et al.; ``benchmarks/segmentation.py``, seed 0: point
   accuracy +0.01 to +0.05 on 10 of the 36 forest stands, most at 2
   points/m2, none lower, detection F1 within 0.003; MixedConifer IoU with
   lidR 0.589 -> 0.594, trees unchanged), before the small trees are judged:
   a small tree with a tree within reach is judged by its own points (loose
   returns around a fragment do not make it a tree), one with none, by those
   attached to it too (a spire over the lower crown a sparse scan cut off
   from it; figures in step 3).  Finally the plateau rule of step 4
   is judged again on the finished crowns (:func:`.cleanup.merge_plateaus`):
   a tree whose top is within ``merge_plateau`` (5 %) of a neighbour's
   height and ``PLATEAU_REACH`` (1.3) of its crown radii, and whose crown
   touches that neighbour's (points within ``radius_m``) less than half
   ``merge_prominence`` (7.5 % of its height) below its top, rises nowhere
   above the crown it touches (no prominence above their saddle): a leader
   or a flank of one flat crown, merged into it.  The cut judges that saddle
   on its start partition, before the cuts and clean-up move the boundary;
   on the finished crowns 20 of the 25 pieces left in the open broadleaf
   stand at 20 points/m2 have their top within 2 % of a taller crown's
   points.  Sylva, not in Hu et al.; ``benchmarks/segmentation.py`` (seed 0):
   the 36 forest stands' mean F1 0.874 -> 0.884 at 5 points/m2 and more
   (open mixed at 5 / 20 / 50: 0.846 / 0.867 / 0.828 -> 0.874 / 0.899 /
   0.858, medium broadleaf at 20: 0.895 -> 0.915), 0.774 -> 0.779 at 2,
   point accuracy +0.010; the most a stand loses is 0.009 (open broadleaf
   at 2 points/m2) and 0.006 (dense conifers at 50); parkland +0.014 /
   +0.021 (forest defaults) and +0.012 / +0.015 (open-grown); the shipped
   sample unchanged; MixedConifer 275 -> 271 trees, IoU 0.594 -> 0.593;
   autzen_trim 285 -> 278 trees.  Where the canopy around a top is closed,
   the rule judges a tree as one at most ``CLOSED_HEIGHT_M`` (26.8 m) high,
   as the cut's merges do (its crown radius, and how level and how deep
   below its top a contact is): judged by 50 m, two tall conifers touching
   3.7 m below their tops were one flat crown.  Tall dense stands at 5 / 20
   / 50 points/m2 0.763 / 0.788 / 0.772 -> 0.769 / 0.801 / 0.783 (seed 0),
   0.654 / 0.719 / 0.718 -> 0.660 / 0.731 / 0.729 (seed 1); no other stand,
   slope, parkland, the sample or MixedConifer changes.
   **Sloping ground.** Heights above the ground tilt a crown on a slope: its
   downhill side rises, and the highest point above ground of a round crown
   lies downhill of its apex (Khosravipour et al. 2015, ISPRS J. 104:44-52),
   off the crown's centre.  The off-centre and plateau rules therefore judge
   a tree from its apex, its highest point in elevation, with heights
   measured from the ground under it (:func:`.cleanup.tree_relative`), and
   the plateau rule compares tops and contacts in elevation (two leaders of
   one crown stand at one elevation, not at one height above a slope);
   heights above ground still give every allometric crown radius.  On level
   ground nothing changes beyond the ground's own undulation.  Sylva, not in
   Hu et al.; ``benchmarks/segmentation.py --slope 30 --kinds
   conifer,broadleaf,mixed --densities 5,20`` (seed 0): mean F1 of the 18
   stands 0.833 -> 0.857 (open broadleaf / mixed at 20 points/m2 0.852 /
   0.836 -> 0.903 / 0.898, dense mixed at 20 0.712 -> 0.744; at most -0.005,
   dense conifers at 5), at 15 degrees 0.849 -> 0.865 (no stand loses); the
   full level suite within 0.007 per stand (mean 0.890 and 0.779 -> 0.780 at 2
   points/m2), the shipped sample 0.981 -> 0.979, MixedConifer unchanged.
   **A tree's apex near its top** (:func:`.cleanup.apex_near_top`; Sylva, not
   in Hu et al.): the top Sylva reports is a tree's highest point in
   elevation, and where two crowns interlock the cut can leave a neighbour's
   leaf clump, a few centimetres higher, on this side of the boundary; on a
   slope the neighbour's uphill crown stands higher still.  That point would
   be the tree's apex, metres from its stem (of the 56 trees of the dense
   broadleaf stand at 20 points/m2 that had a top of their own and were not
   found, 7 were such: their crown whole, their apex a neighbour's point 1.6 to
   3.7 m from their stem).  A tree's apex is therefore its highest point within
   ``APEX_REACH`` (0.75) of the allometric crown radius of one of the tops
   its crown grew from; a point of the tree higher still, with a point of
   another tree within ``APEX_EDGE_M`` (1 m), goes to that tree when that
   tree's own highest point is at least as high.  ``benchmarks/segmentation.py``
   (seed 0): dense conifers at 20 / 50 points/m2 0.917 / 0.876 -> 0.926 /
   0.888, dense broadleaves 0.820 / 0.812 -> 0.831 / 0.828, tall medium at 50
   0.845 -> 0.853; the conifer, broadleaf and mixed stands' mean at 5
   points/m2 and more 0.894 -> 0.898; on a 30 degree slope 0.857 -> 0.869
   (dense conifers at 20 0.847 -> 0.882, dense broadleaves at 50 0.680 ->
   0.739); the most a stand loses is 0.008 (parkland dense at 5, open
   broadleaves at 2 and open mixed at 5 on the slope); the shipped sample and
   MixedConifer unchanged.  0.5 crown radii also judged trees whose top the
   search had placed on a flank, off their apex (mixed dense at 20 -0.005).
6. **Growth.** Every crown radius above comes from the allometry of trees
   grown in a stand.  A tree that grew in the open (park, street, pasture,
   orchard) has a crown about ``OPEN_GROWN`` (2.5) x as wide, which those
   rules cut into several trees.  ``growth="open-grown"`` (GROWTH of
   segmenttrees and the pipeline) scales them by ``crown_scale`` 2.5 and lets
   the graph reach 1.5 m across and 3 m up (``GROWTH_PRESETS``).  Measured
   with ``benchmarks/segmentation.py --kinds parkland --growth open-grown``
   (seed 0): parkland mean F1 0.36 -> 0.73 at 5 points/m2 and more, 0.43 ->
   0.75 at 2; on autzen_trim.laz the park and street crowns come out whole
   but the riverside forest is lumped into wide crowns: a preset for trees
   grown in the open, not a default.

Modules: :mod:`.graph` (steps 1-2 and the tops' voxels), :mod:`.cut` (the start partition, the cuts
and merges, steps 3-4), :mod:`.cleanup` and :mod:`.islands` (step 5) and :mod:`.method` (:class:`NormalizedCut`); the
public names are re-exported here.
"""
from __future__ import annotations

from .cleanup import ATTACH_ROUNDS, TOP_TOLERANCE_M, crown_radius_m
from .cut import FIEDLER_ITERATIONS, PLATEAU_REACH, SETTLED_NCUT
from .graph import DENSITY_HALF_WIDTH_M, VoxelGraph, canopy_density, local_canopy_density, voxel_graph
from .method import APEX_WINDOW_POINTS, MIN_TREE_AREA_M2, NormalizedCut, TOP_CELL_M

__all__ = ["NormalizedCut", "VoxelGraph", "voxel_graph"]
