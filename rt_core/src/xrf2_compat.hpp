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

// The calling thread (the loop's) counts as attached to the real-time core for evl_get_self();
// a no-op with libevl, where the EVL backend attached it.
void markLoopThreadAttached();

} // namespace xrf2
