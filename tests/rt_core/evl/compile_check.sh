#!/bin/sh
# Compile-check the EVL sources (rt_core/src/evl_*.c) against libevl headers, with warnings as
# errors. Usage: tests/rt_core/evl/compile_check.sh [EVL_INCLUDE_DIR...]   (or set XRF_EVL_INCLUDE,
# colon-separated for several directories). Each directory is passed as -I; a libevl install
# (/usr/evl/include) needs only one, a hand-assembled tree may need the libevl include/ and the
# kernel uapi directory. See docs/rt_core/evl.md.
#
# -std=gnu11, not -std=c11: libevl's own headers use GNU C (typeof in evl/atomic.h, useconds_t),
# libevl is itself built with gnu11, and CMake's C_STANDARD 11 (extensions on) passes -std=gnu11.
set -eu
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../../.." && pwd)
CC=${CC:-cc}

dirs=""
if [ "$#" -gt 0 ]; then
    for d in "$@"; do dirs="$dirs:$d"; done
elif [ -n "${XRF_EVL_INCLUDE:-}" ]; then
    dirs=":$XRF_EVL_INCLUDE"
else
    echo "compile_check: give an EVL include directory (argument or XRF_EVL_INCLUDE)" >&2
    exit 2
fi

incs=""
old_ifs=$IFS
IFS=:
for d in $dirs; do
    [ -z "$d" ] && continue
    if [ ! -d "$d" ]; then
        echo "compile_check: $d is not a directory" >&2
        exit 2
    fi
    incs="$incs -I$d"
done
IFS=$old_ifs

set -x
# shellcheck disable=SC2086
"$CC" -std=gnu11 -Wall -Wextra -Werror -fsyntax-only -DXRF_HAVE_EVL=1 \
    -I "$root/rt_core/include" $incs \
    "$root/rt_core/src/evl_backend.c" "$root/rt_core/src/evl_spidev.c"
