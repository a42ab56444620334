#!/bin/sh
# PDAL for the benchmarks on a machine whose distribution does not package it.
#
# Debian 12 and 13 and their PyPI mirror have no PDAL (the `pdal` wheel is only the
# Python binding and needs libpdal); Debian 11 packages PDAL 2.2.0. This script, run as
# root, installs Debian 11 and its PDAL in a folder (debootstrap, then apt-get in a
# chroot) and puts a `pdal` command on the PATH that starts that PDAL with Debian 11's
# own dynamic loader and libraries. PDAL then runs in the host's file system, so any
# path (relative, or outside any folder chosen here) works as with a native install.
# The benchmarks (bench_terrain.py, bench_ground.py) find `pdal` and time it as a whole
# process.
#
#     sudo sh scripts/pdal_chroot.sh [ROOT]      (default: /opt/bullseye)
#
# With conda-forge (`conda install -c conda-forge pdal`) or Ubuntu's package, skip this.
set -eu
ROOT=${1:-/opt/bullseye}
LIB=$ROOT/usr/lib/x86_64-linux-gnu

command -v debootstrap >/dev/null || apt-get install -y -qq debootstrap
[ -x "$ROOT/usr/bin/pdal" ] || {
    debootstrap --variant=minbase bullseye "$ROOT" http://deb.debian.org/debian
    cp /etc/resolv.conf "$ROOT/etc/resolv.conf"
    chroot "$ROOT" sh -c "apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends pdal"
}
# Debian's BLAS and LAPACK are chosen by absolute alternatives links, which would
# resolve in the host: their real folders go on the library path instead.
cat > /usr/local/bin/pdal <<EOF2
#!/bin/sh
PROJ_LIB=$ROOT/usr/share/proj GDAL_DATA=$ROOT/usr/share/gdal \\
exec $LIB/ld-linux-x86-64.so.2 --library-path $LIB:$LIB/blas:$LIB/lapack:$ROOT/usr/lib $ROOT/usr/bin/pdal "\$@"
EOF2
chmod +x /usr/local/bin/pdal
pdal --version | sed -n 2p
