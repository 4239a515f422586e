#!/usr/bin/env bash
# ARM check without a Pi (issue 14): build an arm64 Debian bookworm userland (the base of
# Raspberry Pi OS Bookworm) under qemu-user emulation, install the three Lamina packages
# there, run a short simulated scan and the device's tests.
#
# Needs root and the Debian packages debootstrap and qemu-user-static. The userland and its
# venv are cached in $LAMINA_ARM64_CACHE (default ~/.cache/lamina-arm64): the first run takes
# many minutes, later runs only reinstall the Lamina packages. Emulation is ~17x slower than
# native: its times prove nothing about the Pi's speed, only that everything installs and runs.
set -euo pipefail

ROOT=$(cd "$(dirname "$0")/.." && pwd)
CACHE=${LAMINA_ARM64_CACHE:-$HOME/.cache/lamina-arm64}
CHROOT=$CACHE/bookworm-arm64
MIRROR=${LAMINA_ARM64_MIRROR:-http://deb.debian.org/debian}
# python3 for Lamina; the rest is what `import pymeshlab` needs on a minimal system.
APT_PACKAGES=python3,python3-venv,python3-pip,ca-certificates,libgl1,libopengl0,libsm6,libice6,libfontconfig1,libfreetype6,libharfbuzz0b
START=$(date +%s)

say() { echo "arm64-check: $*"; }
fail() { echo "arm64-check: $*" >&2; exit 1; }
elapsed() { echo "$(($(date +%s) - START)) s"; }

[ "$(id -u)" = 0 ] || fail "needs root (debootstrap, chroot, binfmt_misc); run it as root"
for tool in debootstrap qemu-aarch64-static chroot; do
    command -v "$tool" >/dev/null \
        || fail "$tool is missing; install it: apt-get install -y debootstrap qemu-user-static"
done

# The kernel must hand arm64 binaries to qemu: binfmt_misc mounted and an aarch64 entry
# with the F flag (interpreter opened now, so it works inside the chroot).
if [ ! -e /proc/sys/fs/binfmt_misc/register ]; then
    mount -t binfmt_misc binfmt_misc /proc/sys/fs/binfmt_misc \
        || fail "cannot mount binfmt_misc (a container without it cannot run arm64 binaries)"
fi
if [ ! -e /proc/sys/fs/binfmt_misc/qemu-aarch64 ]; then
    conf=/usr/lib/binfmt.d/qemu-aarch64.conf
    [ -r "$conf" ] || fail "no $conf from qemu-user-static; cannot register arm64 emulation"
    grep -v '^#' "$conf" > /proc/sys/fs/binfmt_misc/register \
        || fail "registering $conf with binfmt_misc failed"
fi

if [ ! -e "$CHROOT/.lamina-debootstrap-done" ]; then
    say "building the arm64 bookworm userland in $CHROOT (first run: several minutes)"
    rm -rf "$CHROOT"
    mkdir -p "$CHROOT"
    debootstrap --arch=arm64 --variant=minbase --include="$APT_PACKAGES" \
        bookworm "$CHROOT" "$MIRROR" > "$CACHE/debootstrap.log" 2>&1 \
        || fail "debootstrap failed; see $CACHE/debootstrap.log"
    touch "$CHROOT/.lamina-debootstrap-done"
    say "userland ready after $(elapsed)"
fi

# The pty link between host and device needs /dev/pts inside the chroot.
mounted=()
cleanup() {
    local i
    for ((i = ${#mounted[@]} - 1; i >= 0; i--)); do umount -l "${mounted[i]}" || true; done
}
trap cleanup EXIT
for m in proc dev dev/pts; do
    mountpoint -q "$CHROOT/$m" && continue
    if [ "$m" = proc ]; then mount -t proc proc "$CHROOT/proc"; else mount --bind "/$m" "$CHROOT/$m"; fi
    mounted+=("$CHROOT/$m")
done
cp /etc/resolv.conf "$CHROOT/etc/resolv.conf"
# This machine's certificate bundle, so pip trusts the same registries from inside.
cp /etc/ssl/certs/ca-certificates.crt "$CHROOT/etc/lamina-ca.crt"

# The working tree (tracked and new files, not the venv or outputs) as the Pi would get it.
SRC=$CHROOT/opt/lamina/src
rm -rf "$SRC"
mkdir -p "$SRC"
git -C "$ROOT" ls-files -z --cached --others --exclude-standard \
    | (cd "$ROOT" && tar --null --ignore-failed-read -T - -cf -) | tar -xf - -C "$SRC"

run() { chroot "$CHROOT" /usr/bin/env -i HOME=/root PATH=/opt/lamina/venv/bin:/usr/bin:/bin \
    PIP_CERT=/etc/lamina-ca.crt PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_DEFAULT_TIMEOUT=180 \
    LANG=C.UTF-8 "$@"; }

say "arch inside: $(run uname -m), $(run ldd --version | head -1)"
[ -x "$CHROOT/opt/lamina/venv/bin/python" ] || run python3 -m venv /opt/lamina/venv
say "installing lamina-shared, lamina-device, lamina-host[meshlab] (aarch64 wheels)"
run /bin/sh -c 'cd /opt/lamina/src && pip install --quiet ./shared ./device "./host[meshlab]" \
    pytest hypothesis' > "$CACHE/pip.log" 2>&1 || fail "pip install failed; see $CACHE/pip.log"
run python -c 'import pymeshlab; print("arm64-check: pymeshlab", pymeshlab.__version__ if hasattr(pymeshlab, "__version__") else "imports")'

say "simulated scan: lamina scan --device sim --sections 1 --views 4"
scan_start=$(date +%s)
run /bin/sh -c 'cd /tmp && rm -rf arm64-scan && lamina scan --device sim --sections 1 --views 4 \
    --library /tmp/arm64-scan/library.sqlite -o /tmp/arm64-scan/out' \
    || fail "the simulated scan failed after $(elapsed)"
say "scan took $(($(date +%s) - scan_start)) s (emulated)"

say "device tests"
tests_start=$(date +%s)
# Tests marked wall_clock hold code to a real-time budget (a render's seconds, step pulse
# intervals); under ~17x emulation that says nothing about the Pi, so they are left out
# here (they run in make test).
run /bin/sh -c 'cd /opt/lamina/src && python -m pytest -q -p no:cacheprovider tests/device \
    -m "not wall_clock"' \
    || fail "device tests failed after $(elapsed)"
say "device tests took $(($(date +%s) - tests_start)) s (emulated)"
say "PASS in $(elapsed)"
