"""Write the demo's embedded sample tile: resources/sample/sample.laz + sample_trees.csv.

A 100 m x 100 m synthetic mixed stand (conifers, broadleaves, multi-stem
trees) on a mild slope, scanned at 8 pulses/m2 (about 12 points/m2 with the
multiple returns), ground classified, with intensity, RGB and a little
noise, in UTM 32N (EPSG:32632).  The extra dimensions ``true_tree`` and
``true_kind`` carry the per-point truth, the CSV the per-tree truth.

Deterministic: the seeds are fixed, so running it twice gives byte-identical
files.  Run from the repository root:

    PROJ_DATA=/usr/share/proj .venv/bin/python scripts/make_sample.py
"""
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

try:
    from sylva.testing.synth import CROWN, GROUND, STEM, ScanSpec, StandSpec, make_stand, simulate_scan, write_scan
except ImportError:  # not installed: the repository root is the package
    sys.path.insert(0, str(ROOT.parent))
    from sylva.testing.synth import CROWN, GROUND, STEM, ScanSpec, StandSpec, make_stand, simulate_scan, write_scan

STAND = StandSpec(
    width_m=100.0, depth_m=100.0, stems_per_ha=250, crown_overlap=0.5,
    slope_deg=6.0, slope_azimuth_deg=200.0, undulation_m=0.6, seed=2024,
)
SCAN = ScanSpec(pulse_density=8.0, rgb=True, intensity=True, classify_ground=True,
                noise_fraction=0.001, seed=2024)
LIMIT_BYTES = 2_000_000


def main(folder: Path = ROOT / "resources" / "sample") -> int:
    folder.mkdir(parents=True, exist_ok=True)
    stand = make_stand(STAND)
    scan = simulate_scan(stand, SCAN)
    laz, csv_path = write_scan(scan, folder, "sample")
    size = laz.stat().st_size
    n = len(scan.cloud)
    kinds = np.bincount(scan.truth_kind, minlength=4)
    area = STAND.width_m * STAND.depth_m
    print(f"{laz.relative_to(ROOT)}: {n:,} points ({n / area:.1f} points/m2, "
          f"{scan.n_pulses / area:.1f} pulses/m2), {size:,} bytes ({size / 1e6:.2f} MB)")
    print(f"  ground {kinds[GROUND]:,}, stem {kinds[STEM]:,}, crown {kinds[CROWN]:,}, "
          f"noise {kinds[3]:,}")
    print(f"{csv_path.relative_to(ROOT)}: {len(stand.trees)} trees "
          f"({', '.join(f'{s} {sum(t.species == s for t in stand.trees)}' for s in STAND.species)}), "
          f"{csv_path.stat().st_size:,} bytes")
    if size >= LIMIT_BYTES:
        print(f"error: the sample must stay under {LIMIT_BYTES:,} bytes", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
