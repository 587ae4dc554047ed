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

// A later timestamp s of the same cycle as base (base_ns as a timespec): base plus the offset, an
// add and a carry instead of a division for each of step()'s t2..t7.
inline struct timespec toTimespecAfter(const struct timespec &base, int64_t base_ns, int64_t s)
{
    const int64_t d = s - base_ns;
    if (d < 0 || d >= 1000000000LL)
        return toTimespec(s);
    struct timespec ts = base;
    ts.tv_nsec += (long)d;
    if (ts.tv_nsec >= 1000000000L) {
        ts.tv_nsec -= 1000000000L;
        ts.tv_sec++;
    }
    return ts;
}

// The calling thread (the loop's) counts as attached to the real-time core for evl_get_self();
// a no-op with libevl, where the EVL backend attached it.
void markLoopThreadAttached();

} // namespace xrf2
