#!/usr/bin/env bash
# Install QGIS >= 3.34 (Debian 13 "trixie"'s, 3.40) in a separate root file system, <checkout>/.qgis-trixie,
# for the one check Debian 12's QGIS 3.22 cannot do: opening Sylva's 3D Tiles in QGIS's tiled scene
# layer (tests/test_tiled_scene.py runs scripts/qgis_tiled_scene_check.py in it). The host gets only
# `apt-get install debootstrap`; nothing of trixie touches the host system. Needs root (debootstrap,
# unshare, chroot). Idempotent: a second run only reads a stamp file. Measured on a 2-core machine:
# about 3.5 min (debootstrap ~1.5 min, apt-get ~2 min) and 1.8 GB.
#
# Then, as a second stage with its own stamp (.sylva-desktop-installed), the QGIS 3.40 desktop for
# tests/test_desktop.py's 3.40 lane (every dialog run under Xvfb, tests/desktop/run_dialogs.py): the
# `qgis` desktop, xvfb and xauth, Sylva's Python dependencies from trixie's own packages (numpy 2.2,
# scipy, shapely, pyproj, numba 0.61, trimesh, laspy, scikit-learn, ...) and from PyPI only what
# Debian lacks (lazrs, into /opt/sylva-pip, on sys.path through a .pth file), the plugin folder
# /opt/sylva-plugins/sylva (a link to /sylva, where --run mounts the checkout) and Sylva's numba
# kernels compiled once (python3 -m sylva.plugin.warmup, cache in /var/cache/sylva-numba inside the
# root). A failure there only prints a warning (exit 0): the 3.40 desktop tests then skip, saying why.
# Measured from scratch on the same 2-core machine (Debian mirror behind a cache): this stage 64 s
# (apt-get 20 s, pip 2 s, kernel warm-up 42 s) and +400 MB; the whole root then takes 2.5 min and 2.1 GB.
#   bash scripts/setup_qgis_trixie.sh                                  install (or check the stamp)
#   bash scripts/setup_qgis_trixie.sh --run [--bind DIR]... CMD ARGS   run CMD inside
#
# --run enters the root in a private mount namespace, so every mount vanishes with the command
# (nothing to tear down): /proc, a fresh tmpfs /tmp (HOME and XDG_RUNTIME_DIR: QGIS writes its
# profile there, so no state persists), the checkout on /sylva and each DIR at its own path (paths
# read the same inside and out). QGIS itself was found to need none of these but the data's folder.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
target="$root/.qgis-trixie"
mirror="${SYLVA_DEBIAN_MIRROR:-http://deb.debian.org/debian}"
# The smallest set that gives QgsTiledSceneLayer, the "cesiumtiles" provider and 2D rendering: the
# provider is in libqgis-core; python3-qgis Depends on qgis-providers and the rest (no Recommends).
debs="python3-qgis"
stamp="$target/.sylva-installed"
want="trixie $debs"
log="${TMPDIR:-/tmp}/sylva-qgis-trixie.log"

run_inside() {
    # A private mount namespace: every mount made here vanishes when the command ends (nothing to
    # tear down). Inside: /proc, a fresh /tmp and /dev/shm, the checkout on /sylva, and each
    # BIND_DIRS folder at its own path (so paths print the same inside and out).
    exec unshare --mount --propagation private -- /bin/sh -euc '
        t="$1"; r="$2"; binds="$3"; shift 3
        mount -t proc proc "$t/proc"
        mount -t tmpfs tmpfs "$t/tmp"
        mkdir -m 700 "$t/tmp/runtime"
        mount -t tmpfs tmpfs "$t/dev/shm" 2>/dev/null || true
        mkdir -p "$t/sylva"
        mount --bind "$r" "$t/sylva"
        for d in $binds; do
            mkdir -p "$t$d"
            mount --bind "$d" "$t$d"
        done
        exec chroot "$t" /usr/bin/env -i PATH=/usr/sbin:/usr/bin:/sbin:/bin HOME=/tmp \
            LANG=C.UTF-8 QT_QPA_PLATFORM=offscreen XDG_RUNTIME_DIR=/tmp/runtime \
            QGIS_PLUGINPATH=/opt/sylva-plugins NUMBA_CACHE_DIR=/var/cache/sylva-numba "$@"
    ' sh "$target" "$root" "$BIND_DIRS" "$@"
}

BIND_DIRS=""
if [ "${1:-}" = "--run" ]; then
    # --run [--bind DIR]... COMMAND ARGS...   (DIR: absolute, no spaces)
    shift
    while [ "${1:-}" = "--bind" ]; do
        d="$(cd "$2" && pwd -P)"
        case "$d" in *" "*) echo "setup_qgis_trixie: --bind $d: no spaces please" >&2; exit 2;; esac
        BIND_DIRS="$BIND_DIRS $d"
        shift 2
    done
    if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
        echo "setup_qgis_trixie: $target is not installed; run bash scripts/setup_qgis_trixie.sh" >&2
        exit 3
    fi
    run_inside "$@"
fi

# The desktop stage (see the header): its packages, the PyPI ones, and what the stamp records.
desktop_debs="qgis qgis-providers xvfb xauth python3-numpy python3-scipy python3-shapely python3-pyproj \
python3-numba python3-trimesh python3-sklearn python3-tifffile python3-geographiclib \
python3-lxml python3-pil python3-pip"
# Not from Debian: lazrs (LAZ; not packaged) and so laspy too: trixie's laspy 2.5.4 wants lazrs 0.6,
# whose parallel decompressor panics (a Rust panic, then QGIS 3.40 died on signal 11 in the dialogs
# test) where lazrs 0.8 raises; laspy 2.7 + lazrs 0.8 are what Debian 12's venv gets. Wheels, no build.
desktop_pip="laspy>=2.7,<2.8 lazrs>=0.8,<0.9"
desktop_stamp="$target/.sylva-desktop-installed"
desktop_failed="$target/.sylva-desktop-failed"
desktop_want="trixie-desktop 2 $desktop_debs $desktop_pip"

if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
    if [ "$(id -u)" -ne 0 ]; then
        echo "setup_qgis_trixie: needs root (debootstrap, chroot)" >&2
        exit 1
    fi
    start=$(date +%s)
    if ! command -v debootstrap >/dev/null 2>&1; then
        echo "setup_qgis_trixie: installing debootstrap (host, Debian package)..."
        apt-get update -qq
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends debootstrap >/dev/null
    fi
    if [ ! -x "$target/usr/bin/apt-get" ] || [ ! -e "$target/.sylva-debootstrapped" ]; then
        echo "setup_qgis_trixie: debootstrap trixie into $target (a few minutes)..."
        rm -rf --one-file-system "$target"
        debootstrap --variant=minbase trixie "$target" "$mirror" >"$log" 2>&1 \
            || { tail -30 "$log" >&2; echo "setup_qgis_trixie: debootstrap failed (log: $log)" >&2; exit 1; }
        touch "$target/.sylva-debootstrapped"
        echo "setup_qgis_trixie: debootstrap took $(( $(date +%s) - start )) s"
    fi
    t_apt=$(date +%s)
    echo "setup_qgis_trixie: installing trixie's $debs inside $target..."
    cp /etc/resolv.conf "$target/etc/resolv.conf" 2>/dev/null || true
    # a throwaway root: no fsync per unpacked file (as container images do), no translations
    echo "force-unsafe-io" > "$target/etc/dpkg/dpkg.cfg.d/sylva-unsafe-io"
    echo 'Acquire::Languages "none";' > "$target/etc/apt/apt.conf.d/99sylva-no-translations"
    ( run_inside /bin/sh -c "apt-get update -qq && DEBIAN_FRONTEND=noninteractive \
          apt-get install -y -qq --no-install-recommends $debs >/dev/null && apt-get clean && rm -rf /var/lib/apt/lists/*" ) \
        >>"$log" 2>&1 \
        || { tail -30 "$log" >&2; echo "setup_qgis_trixie: apt-get inside the trixie root failed (log: $log)" >&2
             exit 1; }
    echo "$want" > "$stamp"
    echo "setup_qgis_trixie: apt-get took $(( $(date +%s) - t_apt )) s; done in $(( $(date +%s) - start )) s," \
        "$(du -sh --one-file-system "$target" | cut -f1)"
fi

[ "${SYLVA_QGIS_TRIXIE_DESKTOP:-1}" = 0 ] && exit 0
if [ "$(cat "$desktop_stamp" 2>/dev/null)" = "$desktop_want" ]; then
    exit 0
fi
desktop_fail() {
    # never fails the set-up: the 3.40 desktop tests read this file and skip with its text
    { echo "$1"; tail -15 "$log"; } > "$desktop_failed"
    echo "setup_qgis_trixie: WARNING: $1 (log: $log); the QGIS 3.40 desktop tests will skip" >&2
    exit 0
}
if [ "$(id -u)" -ne 0 ]; then
    echo "setup_qgis_trixie: the 3.40 desktop stage needs root" >&2
    exit 0
fi
t_desk=$(date +%s)
used_before=$(du -sk --one-file-system "$target" | cut -f1)
echo "setup_qgis_trixie: installing the QGIS 3.40 desktop and Sylva's dependencies inside $target..."
cp /etc/resolv.conf "$target/etc/resolv.conf" 2>/dev/null || true
( run_inside /bin/sh -c "apt-get update -qq && DEBIAN_FRONTEND=noninteractive \
      apt-get install -y -qq --no-install-recommends $desktop_debs >/dev/null && apt-get clean \
      && rm -rf /var/lib/apt/lists/*" ) >>"$log" 2>&1 \
    || desktop_fail "apt-get install of the QGIS 3.40 desktop inside the trixie root failed"
t_pip=$(date +%s)
# pip trusts the host's CA bundle (the certificates the host's own pip trusts, e.g. a proxy's)
host_ca="${PIP_CERT:-${SSL_CERT_FILE:-/etc/ssl/certs/ca-certificates.crt}}"
cert=""
if [ -r "$host_ca" ]; then
    cp "$host_ca" "$target/etc/ssl/sylva-host-ca.crt" && cert="--cert /etc/ssl/sylva-host-ca.crt"
fi
( run_inside /bin/sh -c "rm -rf /opt/sylva-pip && python3 -m pip install -q --disable-pip-version-check \
      --no-cache-dir --root-user-action=ignore --break-system-packages --only-binary=:all: --no-deps $cert --target /opt/sylva-pip \
      $(printf "'%s' " $desktop_pip)" ) >>"$log" 2>&1 || desktop_fail "pip install $desktop_pip inside the trixie root failed"
# on every Python's sys.path in the root (no PYTHONPATH to pass): a .pth in its site-packages
site="$(run_inside python3 -c 'import site; print(site.getsitepackages()[0])' 2>>"$log")" \
    || desktop_fail "the trixie root's python3 does not start"
mkdir -p "$target$site" && echo /opt/sylva-pip > "$target$site/sylva-pip.pth"
# the plugin folder QGIS 3.40 loads: QGIS_PLUGINPATH=/opt/sylva-plugins (run_inside sets it) holds
# "sylva", a link to the checkout that --run mounts on /sylva
mkdir -p "$target/opt/sylva-plugins" "$target/var/cache/sylva-numba"
ln -sfn /sylva "$target/opt/sylva-plugins/sylva"
( run_inside python3 -c "import laspy, lazrs, numba, numpy, scipy, shapely, pyproj, trimesh, sklearn, tifffile
import sys; sys.path.insert(0, '/opt/sylva-plugins'); import sylva.algorithms
print('numpy', numpy.__version__, 'numba', numba.__version__, 'laspy', laspy.__version__)" ) >>"$log" 2>&1 \
    || desktop_fail "Sylva does not import in the trixie root's Python 3.13"
t_warm=$(date +%s)
echo "setup_qgis_trixie: compiling Sylva's numba kernels for the root's Python (a few minutes)..."
( run_inside /usr/bin/env PYTHONPATH=/opt/sylva-plugins OMP_NUM_THREADS=1 \
      python3 -m sylva.plugin.warmup --if-needed ) >>"$log" 2>&1 \
    || desktop_fail "python3 -m sylva.plugin.warmup failed in the trixie root"
rm -f "$desktop_failed"
echo "$desktop_want" > "$desktop_stamp"
echo "setup_qgis_trixie: desktop stage: apt-get $(( t_pip - t_desk )) s, pip $(( t_warm - t_pip )) s," \
    "warm-up $(( $(date +%s) - t_warm )) s; +$(( ($(du -sk --one-file-system "$target" | cut -f1) - used_before) / 1024 )) MB"
