#!/usr/bin/env bash
# Install everything (idempotent) and run Sylva's whole test suite, QGIS tests included.
# Extra arguments go to pytest, e.g.  bash scripts/test.sh -k treetops
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/setup.sh" --viewers
cd "$root"
# shellcheck source=scripts/env.sh
. scripts/env.sh
exec .venv/bin/pytest "$@"
