# Cross-building rt_core and student controllers for a Raspberry Pi 4 (arm64) on an x86 machine,
# with Debian's cross compiler (g++-aarch64-linux-gnu) and qemu-user (qemu-aarch64):
#
#   cmake -S rt_core -B build-arm64 \
#         -DCMAKE_TOOLCHAIN_FILE=rt_core/cmake/toolchains/aarch64-linux-gnu.cmake
#
# ./lab test builds this way on every run (tests/rt_core/test_arm64.py): the aarch64 compiler
# warns where x86's does not, and a missing barrier shows only on a weakly ordered CPU.
# A Pi builds natively and needs no toolchain file.
set(CMAKE_SYSTEM_NAME Linux)
set(CMAKE_SYSTEM_PROCESSOR aarch64)

set(XRF_CROSS_TRIPLE aarch64-linux-gnu)
set(CMAKE_C_COMPILER ${XRF_CROSS_TRIPLE}-gcc)
set(CMAKE_CXX_COMPILER ${XRF_CROSS_TRIPLE}-g++)

# Debian's multiarch cross libraries live under /usr/<triple>; the host's /usr/lib must not be
# searched for libraries or headers (an x86 libpthread would link and fail at run time).
set(CMAKE_FIND_ROOT_PATH /usr/${XRF_CROSS_TRIPLE})
set(CMAKE_FIND_ROOT_PATH_MODE_PROGRAM NEVER)
set(CMAKE_FIND_ROOT_PATH_MODE_LIBRARY ONLY)
set(CMAKE_FIND_ROOT_PATH_MODE_INCLUDE ONLY)
# Packages (XrfRt) are found where the caller points XrfRt_DIR or CMAKE_PREFIX_PATH, not only
# below the root path: a cross-built rt_core is installed into an ordinary folder.
set(CMAKE_FIND_ROOT_PATH_MODE_PACKAGE BOTH)

# CTest and try_run start target programs through qemu-user; -L: where the aarch64 loader and
# libc are (Debian's libc6-arm64-cross).
set(CMAKE_CROSSCOMPILING_EMULATOR qemu-aarch64 -L /usr/${XRF_CROSS_TRIPLE})
