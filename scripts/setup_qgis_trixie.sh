#!/usr/bin/env bash
# Install QGIS >= 3.34 (Debian 13 "trixie"'s, 3.40) in a separate root file system, <checkout>/.qgis-trixie,
# for the one check Debian 12's QGIS 3.22 cannot do: opening Sylva's 3D Tiles in QGIS's tiled scene
# layer (tests/test_tiled_scene.py runs scripts/qgis_tiled_scene_check.py in it). The host gets only
# `apt-get install debootstrap`; nothing of trixie touches the host system. Needs root (debootstrap,
# unshare, chroot). Idempotent: a second run only reads a stamp file. Measured on a 2-core machine:
# about 3.5 min (debootstrap ~1.5 min, apt-get ~2 min) and 1.8 GB.
#
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
            LANG=C.UTF-8 QT_QPA_PLATFORM=offscreen XDG_RUNTIME_DIR=/tmp/runtime "$@"
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

if [ "$(cat "$stamp" 2>/dev/null)" = "$want" ]; then
    exit 0
fi
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
