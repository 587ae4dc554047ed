/*
 * EVL LOOK-ALIKE for CI (tests/rt_core/evl/lookalike) -- NOT libevl, and never installed on a Pi.
 *
 * Written here from libevl's documented API (names, signatures, return conventions); no code,
 * header or text of libevl was copied or fetched. It declares exactly what rt_core's evl backend
 * (src/evl_backend.c, src/evl_spidev.c) and the XRF2 headers/student API use, so that CI builds,
 * installs, links and runs the XRF_HAVE_EVL build path. libevl.c implements it on plain Linux;
 * docs/rt_core/evl.md says what it emulates and what it cannot.
 *
 * Conventions kept from libevl: evl_* calls return 0 / a descriptor, or -errno; oob_read,
 * oob_write and oob_ioctl return -1 and set errno.
 */
#ifndef XRF_EVL_LOOKALIKE_EVL_H
#define XRF_EVL_LOOKALIKE_EVL_H

#include <evl/syscall.h>
#include <evl/factory.h>
#include <evl/clock.h>
#include <evl/sched.h>
#include <evl/thread.h>
#include <evl/proxy.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Binds the process to the core; also locks its memory (mlockall). Idempotent. */
int evl_init(void);

#ifdef __cplusplus
}
#endif

#endif
