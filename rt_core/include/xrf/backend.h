/*
 * xrf/backend.h — what the loop needs from the real-time kernel: thread set-up, a monotonic
 * clock, an absolute sleep, and a way to ring the host's doorbell without leaving real-time mode.
 * posix: SCHED_FIFO + clock_nanosleep(TIMER_ABSTIME); evl: libevl (built where libevl exists).
 */
#ifndef XRF_BACKEND_H
#define XRF_BACKEND_H

#include <signal.h>
#include <stdint.h>

#include "xrf/channels.h"

#ifdef __cplusplus
extern "C" {
#endif

struct xrf_rt_config {
    int cpu;                 /* pin the loop thread to this CPU; -1: leave affinity as it is */
    int priority;            /* SCHED_FIFO priority 1..99; 0: keep the thread's current policy */
    int lock_memory;         /* mlockall(MCL_CURRENT | MCL_FUTURE) */
    uint32_t stack_prefault; /* bytes of stack to touch before the first cycle */
};

struct xrf_backend {
    const char *name;
    /* Called on the loop thread before the first cycle; may print. Returns 0, or -errno for a
     * fatal problem. Sets *rt_sched to 1 when real-time scheduling is in force. */
    int (*thread_setup)(const struct xrf_rt_config *cfg, int *rt_sched);
    int64_t (*now_ns)(void);
    /* Sleep until the absolute CLOCK_MONOTONIC time; returns 0 or -errno. */
    int (*sleep_until)(int64_t abs_ns);
    /* Wake the host side waiting on shm's doorbell. */
    void (*ring_doorbell)(struct xrf_shm *shm);
    /* Switches to in-band mode since thread_setup (EVL_T_WOSS); 0 on posix. */
    uint64_t (*demotions)(void);
    /* Doorbell rings the backend could not pass on (EVL: the proxy refused the write, its ring
     * full); the host still wakes on a later one. NULL: never happens (posix). */
    uint64_t (*doorbell_dropped)(void);
    void (*thread_teardown)(void);
};

const struct xrf_backend *xrf_backend_posix(void);
/* NULL in builds without libevl. */
const struct xrf_backend *xrf_backend_evl(void);
/* Simulated time (docs/rt_core/runtime.md): never sleeps, skips each cycle's idle time. Chosen by
 * the runtime for XRF_VIRTUAL_TIME on the simulated board only; bind gives it the run's channels
 * (the host's hold, the log ring's fill, the heartbeat) and the stop flag, before the loop. */
const struct xrf_backend *xrf_backend_virtual(void);
void xrf_backend_virtual_bind(struct xrf_shm *shm, volatile sig_atomic_t *stop);
int64_t xrf_virtual_now_ns(void);  /* the loop's clock in simulated time */
int64_t xrf_virtual_real_ns(void); /* CLOCK_MONOTONIC */

/* "posix", "evl" or "auto" (evl when built with it and /dev/evl exists). NULL if unknown. */
const struct xrf_backend *xrf_backend_by_name(const char *name);

#ifdef __cplusplus
}
#endif

#endif /* XRF_BACKEND_H */
