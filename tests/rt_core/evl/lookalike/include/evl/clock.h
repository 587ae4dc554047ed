/* EVL look-alike for CI, not libevl (see evl/evl.h): the built-in clocks. */
#ifndef XRF_EVL_LOOKALIKE_CLOCK_H
#define XRF_EVL_LOOKALIKE_CLOCK_H

#include <time.h>
#include <unistd.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Built-in clocks are named by negated POSIX clock ids (not descriptors). */
#define EVL_CLOCK_MONOTONIC (-CLOCK_MONOTONIC)
#define EVL_CLOCK_REALTIME (-CLOCK_REALTIME)

int evl_read_clock(int clockfd, struct timespec *tp);
int evl_sleep_until(int clockfd, const struct timespec *timeout);
int evl_get_clock_resolution(int clockfd, struct timespec *tp);
int evl_usleep(useconds_t usecs);
int evl_udelay(unsigned int usecs);

#ifdef __cplusplus
}
#endif

#endif
