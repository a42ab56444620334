#!/bin/sh
# PDAL for the benchmarks on a machine whose distribution does not package it.
#
# Debian 12 and 13 and their PyPI mirror have no PDAL (the `pdal` wheel is only the
# Python binding and needs libpdal); Debian 11 packages PDAL 2.2.0. This script, run as
# root, puts Debian 11 in a chroot, installs PDAL there, binds /tmp and /work into it so
# paths are the same inside and out, and puts a `pdal` command on the PATH that runs the
# chroot's. The benchmarks (bench_terrain.py, bench_ground.py) then find `pdal` and
# time it as a whole process; the chroot adds no measurable time.
#
#     sudo sh scripts/pdal_chroot.sh [ROOT] [BIND...]      (defaults: /opt/bullseye, /tmp /work)
#
# With conda-forge (`conda install -c conda-forge pdal`) or Ubuntu's package, skip this.
set -eu
ROOT=${1:-/opt/bullseye}
[ $# -gt 0 ] && shift
BINDS=${*:-/tmp /work}

command -v debootstrap >/dev/null || apt-get install -y -qq debootstrap
[ -x "$ROOT/usr/bin/pdal" ] || {
    debootstrap --variant=minbase bullseye "$ROOT" http://deb.debian.org/debian
    cp /etc/resolv.conf "$ROOT/etc/resolv.conf"
    chroot "$ROOT" sh -c "apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends pdal"
}
for dir in $BINDS; do
    mkdir -p "$ROOT$dir"
    mountpoint -q "$ROOT$dir" || mount --bind "$dir" "$ROOT$dir"
done
cat > /usr/local/bin/pdal <<EOF
#!/bin/sh
exec chroot $ROOT /usr/bin/pdal "\$@"
EOF
chmod +x /usr/local/bin/pdal
pdal --version | sed -n 2p
