// Helpers for the XRF2-compatible classes (internal to rt_core).
#pragma once

#include <cstdint>
#include <ctime>

namespace xrf2
{

// A loop timestamp (ns on the monotonic clock) as XRF2's struct timespec members hold it.
inline struct timespec toTimespec(int64_t ns)
{
    struct timespec ts;
    ts.tv_sec = (time_t)(ns / 1000000000LL);
    ts.tv_nsec = (long)(ns % 1000000000LL);
    return ts;
}

// A timestamp of the same cycle, d ns after base (base_ns as a timespec): base's nanoseconds plus
// the offset, an add and one unsigned compare instead of a division for each of step()'s t2..t7.
// Exact either way: when the sum leaves base's second (a carry, rare) the division does it.
inline struct timespec toTimespecAfter(const struct timespec &base, int64_t base_ns, int64_t d)
{
    const int64_t ns = (int64_t)base.tv_nsec + d;
    if ((uint64_t)ns >= 1000000000ULL)
        return toTimespec(base_ns + d);
    struct timespec ts;
    ts.tv_sec = base.tv_sec;
    ts.tv_nsec = (long)ns;
    return ts;
}

// The calling thread (the loop's) counts as attached to the real-time core for evl_get_self();
// a no-op with libevl, where the EVL backend attached it.
void markLoopThreadAttached();

} // namespace xrf2
