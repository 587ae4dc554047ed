/*
 * <evl/evl.h> for builds without libevl: a thin POSIX equivalent of the libevl calls XRF2 student
 * code makes, under libevl's names and signatures and with their meaning on a plain Linux thread.
 * On a Pi built with libevl (XRF_HAVE_EVL) this folder is not on the include path and the real
 * <evl/evl.h> is used instead. Covered (docs/students/xrf2-api.md lists them):
 *
 *   evl_init, evl_attach_self / evl_attach_thread, evl_detach_self, evl_get_self,
 *   evl_switch_oob / evl_switch_inband / evl_is_inband, evl_read_clock, evl_sleep_until,
 *   evl_usleep, evl_udelay, evl_get_clock_resolution, evl_set_schedattr / evl_get_schedattr,
 *   evl_yield, evl_printf / evl_vprintf, EVL_CLOCK_MONOTONIC / EVL_CLOCK_REALTIME,
 *   EVL_CLONE_PRIVATE / EVL_CLONE_PUBLIC, struct evl_sched_attrs.
 *
 * Return values follow libevl: 0 (or a descriptor) on success, a negative errno on failure.
 * The clock calls read CLOCK_MONOTONIC / CLOCK_REALTIME through the vDSO (no system call), the
 * clock the loop's own deadlines are on, so a student's evl_read_clock() compares with the
 * loop's wakeup_time, t1..t7 and start_time.
 */
#ifndef XRF_EVL_POSIX_EVL_H
#define XRF_EVL_POSIX_EVL_H

#include <errno.h>
#include <sched.h>
#include <stdarg.h>
#include <stdbool.h>
#include <stddef.h>
#include <sys/types.h>
#include <time.h>
#include <unistd.h>

#ifdef __cplusplus
extern "C" {
#endif

/* libevl names its built-in clocks by negated POSIX clock ids. */
#define EVL_CLOCK_MONOTONIC (-CLOCK_MONOTONIC)
#define EVL_CLOCK_REALTIME (-CLOCK_REALTIME)

#define EVL_CLONE_PUBLIC (1 << 16)
#define EVL_CLONE_PRIVATE (0 << 16)

struct evl_sched_attrs {
    int sched_policy;
    int sched_priority;
};

/* libevl's evl_init also locks the process's memory; so does this one. */
int evl_init(void);

/* The calling thread "joins the real-time core": here it gets a descriptor (its thread id) that
 * evl_get_self() returns from then on. Scheduling is left as it is (the runtime or main set it). */
int evl_attach_thread(int flags, const char *fmt, ...) __attribute__((format(printf, 2, 3)));
int evl_attach_self(const char *fmt, ...) __attribute__((format(printf, 1, 2)));
int evl_detach_self(void);
/* The caller's descriptor, or -EPERM when it is not attached. The loop thread is attached from
 * the first cycle on, as XRF2's loop() attached it. */
int evl_get_self(void);

/* Without a real-time core every thread is in-band: switching is a no-op that succeeds. */
int evl_switch_oob(void);
int evl_switch_inband(void);
bool evl_is_inband(void);

/* SCHED_FIFO / SCHED_RR / SCHED_OTHER of the thread `efd` (the caller's own descriptor, or 0 for
 * the caller); other policies are -EINVAL. */
int evl_set_schedattr(int efd, const struct evl_sched_attrs *attrs);
int evl_get_schedattr(int efd, struct evl_sched_attrs *attrs);
int evl_yield(void);

/* Text into the run's monitor stream (never blocks the loop; printed in-band, like libevl's). */
int evl_printf(const char *fmt, ...) __attribute__((format(printf, 1, 2)));
int evl_vprintf(const char *fmt, va_list ap);

static inline clockid_t xrf_evl_posix_clock(int clockfd)
{
    return clockfd == EVL_CLOCK_REALTIME ? CLOCK_REALTIME : CLOCK_MONOTONIC;
}

static inline int xrf_evl_posix_known_clock(int clockfd)
{
    return clockfd == EVL_CLOCK_MONOTONIC || clockfd == EVL_CLOCK_REALTIME;
}

static inline int evl_read_clock(int clockfd, struct timespec *tp)
{
    if (!xrf_evl_posix_known_clock(clockfd))
        return -EBADF;
    return clock_gettime(xrf_evl_posix_clock(clockfd), tp) == 0 ? 0 : -errno;
}

static inline int evl_get_clock_resolution(int clockfd, struct timespec *tp)
{
    if (!xrf_evl_posix_known_clock(clockfd))
        return -EBADF;
    return clock_getres(xrf_evl_posix_clock(clockfd), tp) == 0 ? 0 : -errno;
}

/* Sleeps until the absolute time `timeout` on the clock. */
static inline int evl_sleep_until(int clockfd, const struct timespec *timeout)
{
    if (!xrf_evl_posix_known_clock(clockfd))
        return -EBADF;
    int r;
    do
        r = clock_nanosleep(xrf_evl_posix_clock(clockfd), TIMER_ABSTIME, timeout, NULL);
    while (r == EINTR);
    return -r;
}

static inline int evl_usleep(useconds_t usecs)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    t.tv_sec += usecs / 1000000;
    t.tv_nsec += (long)(usecs % 1000000) * 1000;
    if (t.tv_nsec >= 1000000000L) {
        t.tv_nsec -= 1000000000L;
        t.tv_sec++;
    }
    return evl_sleep_until(EVL_CLOCK_MONOTONIC, &t);
}

/* Busy-waits (libevl's evl_udelay does not sleep either). */
static inline int evl_udelay(unsigned int usecs)
{
    struct timespec t0, t;
    clock_gettime(CLOCK_MONOTONIC, &t0);
    const long long end =
        (long long)t0.tv_sec * 1000000000LL + t0.tv_nsec + (long long)usecs * 1000LL;
    do
        clock_gettime(CLOCK_MONOTONIC, &t);
    while ((long long)t.tv_sec * 1000000000LL + t.tv_nsec < end);
    return 0;
}

#ifdef __cplusplus
}
#endif

#endif /* XRF_EVL_POSIX_EVL_H */
