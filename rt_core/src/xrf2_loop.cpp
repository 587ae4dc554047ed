// XenoFrtLoop: the fixed-grid periodic loop.
#include "XenoFrtLoop.hpp"

#include <cstdio>

#include "xrf/runtime.hpp"
#include "xrf2_compat.hpp"

namespace
{

// Deadline k of the grid, exact for any frequency: no accumulated rounding, no drift.
inline int64_t gridTime(int64_t t0, uint64_t k, unsigned freq)
{
    return t0 + (int64_t)(k / freq) * 1000000000LL + (int64_t)((k % freq) * 1000000000ULL / freq);
}

// The first deadline after t (t >= t0): where the loop goes on after an overrun. Called only
// then, so its divisions cost nothing in a cycle on time. The estimate from whole seconds and the
// remainder never lies after t (both round down as gridTime does); the while steps on to the
// first deadline after t, against gridTime itself, in a step or two.
inline uint64_t firstDeadlineAfter(int64_t t0, int64_t t, unsigned freq)
{
    const uint64_t d = (uint64_t)(t - t0);
    uint64_t k = (d / 1000000000ULL) * freq + (d % 1000000000ULL) * freq / 1000000000ULL;
    while (gridTime(t0, k, freq) <= t)
        k++;
    return k;
}

} // namespace

XenoFrtLoop::XenoFrtLoop(unsigned cycle_time_freq)
    : cycle_time_freq(cycle_time_freq), xrf_cycle_freq_(cycle_time_freq)
{
}

int XenoFrtLoop::loop()
{
    xrf::Runtime &rt = xrf::Runtime::instance();
    const unsigned freq = rt.effectiveFrequency(xrf_cycle_freq_);
    if (freq == 0) {
        std::fprintf(stderr, "xrf: cycle frequency 0: the loop cannot run (set a frequency)\n");
        return -22;
    }
    xrf_cycle_freq_ = freq;
    cycle_time_freq = freq;
    int r = rt.enter(freq);
    if (r != 0) {
        rt.leave();
        return r;
    }
    // XRF2's loop() attached its thread to the real-time core; code in the hooks may ask
    // evl_get_self() for it (the EVL backend attached it for real in enter()).
    xrf2::markLoopThreadAttached();

    const int64_t t0 = rt.now();
    start_time = xrf2::toTimespec(t0);
    uint64_t k = 0; // the period this cycle belongs to: it slept until gridTime(t0, k)
    int64_t deadline = t0;
    for (;;) {
        const int64_t wake = rt.now();
        wakeup_time = xrf2::toTimespec(deadline);
        rt.beginCycle(wake);
        rt.takeParams(); // a pending parameter set lands here, before the controller computes
        const int ret = step();
        const int64_t end = rt.now();
        idle_time = xrf2::toTimespec(end);
        // Firm deadlines (docs/rt_core/runtime.md, "After an overrun"): a cycle that woke or
        // ended after the next period had begun has lost that period and every other one that
        // began meanwhile. They are not run late, back to back: the next cycle starts at the
        // first period boundary still ahead, on the same grid, and the periods passed over are
        // counted as missed (status, timing log, summary line). The controller sees the real
        // step in wakeup_time (a whole number of periods).
        uint64_t k_next = k + 1;
        int64_t next = gridTime(t0, k_next, freq);
        if (end > next) {
            k_next = firstDeadlineAfter(t0, end, freq);
            next = gridTime(t0, k_next, freq);
        }
        rt.endCycle(wake, deadline, end, k_next - k - 1, next - end);
        if (ret != 0 || rt.stopRequested())
            break;
        // In simulated time the backend's wait also holds the loop for its host.
        rt.sleepUntil(next);
        k = k_next;
        deadline = next;
    }
    xrfAfterLastCycle();
    const int64_t stop = rt.now();
    const int64_t total = stop - t0;
    stop_time = xrf2::toTimespec(stop);
    run_time = xrf2::toTimespec(total);
    rt.leave();
    std::printf("xrf: run time %lld s %lld ns, %llu cycles, %llu missed\n",
                (long long)(total / 1000000000LL), (long long)(total % 1000000000LL),
                (unsigned long long)rt.cycle(), (unsigned long long)rt.missed());
    std::fflush(stdout);
    return 0;
}

int XenoFrtLoop::getCyclesCount() const
{
    return (int)xrf::Runtime::instance().cycle();
}

int XenoFrtLoop::getMissedCycles() const
{
    return (int)xrf::Runtime::instance().missed();
}
