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
    uint64_t k = 0;
    for (;;) {
        const int64_t deadline = gridTime(t0, k, freq);
        const int64_t wake = rt.now();
        wakeup_time = xrf2::toTimespec(deadline);
        rt.beginCycle(wake);
        rt.takeParams(); // a pending parameter set lands here, before the controller computes
        const int ret = step();
        const int64_t end = rt.now();
        idle_time = xrf2::toTimespec(end);
        const int64_t next = gridTime(t0, k + 1, freq);
        const bool missed = end > next;
        rt.endCycle(wake, deadline, end, missed, missed ? 0 : next - end);
        k++;
        if (ret != 0 || rt.stopRequested())
            break;
        // An overrun starts the next cycle at once; the grid itself never moves.
        // In simulated time the backend's wait also holds the loop for its host: never skipped.
        if (!missed || rt.virtualTime())
            rt.sleepUntil(next);
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
