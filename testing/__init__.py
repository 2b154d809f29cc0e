"""Test and benchmark stands (not used by the plugin at run time).

:mod:`sylva.testing.crowns` grows stands of broadleaf crowns made of leaf
clumps (round, flat-topped, cylindrical, several leaders), mixed with
conifers and suppressed trees, on top of :mod:`sylva.core.synth`'s terrain,
stem placement and scan simulator.
"""
