/*
 * posix backend: SCHED_FIFO, mlockall and clock_nanosleep(TIMER_ABSTIME) on plain Linux (with or
 * without PREEMPT_RT). Used on every machine without EVL; when real-time scheduling is refused the
 * loop still runs, with one clear warning, so a laptop or CI behaves like the bench minus the
 * latency guarantees.
 */
#define _GNU_SOURCE
#include "xrf/backend.h"

#include <errno.h>
#include <pthread.h>
#include <sched.h>
#include <stdio.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/prctl.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

static int64_t posix_now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts); /* vDSO: no system call */
    return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

static int posix_sleep_until(int64_t abs_ns)
{
    struct timespec ts = {(time_t)(abs_ns / 1000000000LL), (long)(abs_ns % 1000000000LL)};
    int r;
    do {
        r = clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL);
    } while (r == EINTR);
    return -r;
}

static void posix_ring_doorbell(struct xrf_shm *shm)
{
    xrf_doorbell_wake(shm);
}

static uint64_t posix_demotions(void)
{
    return 0; /* there is no in-band/out-of-band split on plain Linux */
}

static int posix_thread_setup(const struct xrf_rt_config *cfg, int *rt_sched)
{
    *rt_sched = 0;
    if (cfg->cpu >= 0) {
        cpu_set_t set;
        CPU_ZERO(&set);
        CPU_SET(cfg->cpu, &set);
        int r = pthread_setaffinity_np(pthread_self(), sizeof set, &set);
        if (r != 0)
            fprintf(stderr, "xrf: warning: cannot pin the loop to CPU %d: %s\n", cfg->cpu,
                    strerror(r));
    }
    if (cfg->lock_memory && mlockall(MCL_CURRENT | MCL_FUTURE) != 0)
        fprintf(stderr, "xrf: warning: mlockall failed (%s): page faults may add latency\n",
                strerror(errno));

    int policy = 0;
    struct sched_param sp;
    memset(&sp, 0, sizeof sp);
    if (cfg->priority > 0) {
        sp.sched_priority = cfg->priority;
        int r = pthread_setschedparam(pthread_self(), SCHED_FIFO, &sp);
        if (r != 0)
            fprintf(stderr,
                    "xrf: WARNING: real-time scheduling (SCHED_FIFO %d) refused: %s. The loop "
                    "runs anyway, without timing guarantees. Give the process CAP_SYS_NICE or "
                    "an rtprio limit (see docs/rt_core/runtime.md).\n",
                    cfg->priority, strerror(r));
    }
    if (pthread_getschedparam(pthread_self(), &policy, &sp) == 0 &&
        (policy == SCHED_FIFO || policy == SCHED_RR))
        *rt_sched = 1;
    else if (cfg->priority <= 0)
        fprintf(stderr, "xrf: WARNING: the loop thread has no real-time scheduling (policy "
                        "SCHED_OTHER): it runs, but without timing guarantees. Set XRF_PRIO or "
                        "start it from a main that creates a SCHED_FIFO thread.\n");

    /* Timer slack: Linux may end a SCHED_OTHER thread's sleep up to 50 us late (by default) to
     * merge wake-ups. Current kernels give a SCHED_FIFO thread none; a loop whose SCHED_FIFO was
     * refused (a laptop, CI) would have it, so the thread asks for 1 ns whatever its policy.
     * Once, in set-up: no call in the cycle. */
    if (prctl(PR_SET_TIMERSLACK, 1UL, 0UL, 0UL, 0UL) != 0)
        fprintf(stderr, "xrf: warning: cannot lower the timer slack: %s\n", strerror(errno));

    /* Touch the stack now so that a first deep call in a hook does not page-fault mid-cycle. */
    if (cfg->stack_prefault > 0) {
        volatile unsigned char *probe = __builtin_alloca(cfg->stack_prefault);
        for (uint32_t i = 0; i < cfg->stack_prefault; i += 4096)
            probe[i] = 0;
    }
    return 0;
}

static void posix_thread_teardown(void) {}

static const struct xrf_backend posix_backend = {
    .name = "posix",
    .thread_setup = posix_thread_setup,
    .now_ns = posix_now_ns,
    .sleep_until = posix_sleep_until,
    .ring_doorbell = posix_ring_doorbell,
    .demotions = posix_demotions,
    .thread_teardown = posix_thread_teardown,
};

const struct xrf_backend *xrf_backend_posix(void)
{
    return &posix_backend;
}

#ifndef XRF_HAVE_EVL
const struct xrf_backend *xrf_backend_evl(void)
{
    return NULL;
}
#endif

const struct xrf_backend *xrf_backend_by_name(const char *name)
{
    if (name == NULL || name[0] == '\0' || strcmp(name, "auto") == 0) {
        struct stat st;
        const struct xrf_backend *evl = xrf_backend_evl();
        if (evl != NULL && stat("/dev/evl", &st) == 0)
            return evl;
        return &posix_backend;
    }
    if (strcmp(name, "posix") == 0)
        return &posix_backend;
    if (strcmp(name, "evl") == 0)
        return xrf_backend_evl();
    return NULL;
}
