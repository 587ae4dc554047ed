#!/bin/sh
# Builds the EVL look-alike (a CI stand-in for libevl, not libevl) into PREFIX with the layout of
# a libevl install: PREFIX/include/evl/*.h and PREFIX/lib/libevl.so. Then
#   cmake -S rt_core -B build -DXRF_EVL_PREFIX=PREFIX        (or XRF_EVL_PREFIX=PREFIX xrf build)
# takes rt_core's XRF_HAVE_EVL path. Usage: tests/rt_core/evl/lookalike/build.sh PREFIX
set -eu
[ "$#" -eq 1 ] || { echo "usage: $0 PREFIX" >&2; exit 2; }
here=$(cd "$(dirname "$0")" && pwd)
prefix=$1
CC=${CC:-cc}
mkdir -p "$prefix/include" "$prefix/lib"
cp -R "$here/include/evl" "$prefix/include/"
# -fvisibility=hidden: only the libevl API (LA_EXPORT) leaves the library.
"$CC" -std=gnu11 -O2 -g -Wall -Wextra -Werror -fPIC -shared -pthread -fvisibility=hidden \
    -I "$here/include" -o "$prefix/lib/libevl.so" "$here/libevl.c"
