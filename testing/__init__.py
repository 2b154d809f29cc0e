"""Test and benchmark stands (not used by the plugin at run time).

:mod:`sylva.testing.crowns` grows stands of broadleaf crowns made of leaf
clumps (round, flat-topped, cylindrical, several leaders), mixed with
conifers and suppressed trees, on top of :mod:`sylva.testing.synth`'s terrain,
stem placement and scan simulator.
:mod:`sylva.testing.synth` is that simulator (stands of conifers and
broadleaves, airborne scans, truth files: it made the bundled sample);
:mod:`sylva.testing.plots` makes terrestrial plot scans with known stems.
"""
