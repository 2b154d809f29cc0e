"""Cost of the damage checks of core/io/las/checks.py (issue 17) next to the read they guard.

    python benchmarks/damage_checks.py [FILE.laz ...]     (default: the bundled sample)

Prints, per file, the best of 5 runs of the bounds check (min/max of the integer records per
axis), of the size + LAZ chunk-table check, of the one-point probe past the header's count,
and of a whole read_las (which includes all three).
"""
import sys
import time
from pathlib import Path

import laspy

from sylva.core.io import las as L

ROOT = Path(__file__).resolve().parents[1]


def best(fn, n=5):
    times = []
    for _ in range(n):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times) * 1e3


def main(paths):
    for path in paths:
        path = Path(path)
        with laspy.open(path) as r:
            header = r.header
            array = r.read().points.array

        bounds = best(lambda: L.check_bounds(path, array, header))
        size = best(lambda: L.check_size(path, header))
        read = best(lambda: L.read_las(path), 3)
        print(f"{path.name}: {len(array):,} points; bounds check {bounds:.2f} ms, size + chunk table "
              f"{size:.2f} ms, read_las {read:.0f} ms (checks {100 * (bounds + size) / read:.2f} % of the read; "
              f"the probe past the count decodes one point)")


if __name__ == "__main__":
    main(sys.argv[1:] or [ROOT / "resources" / "sample" / "sample.laz"])
