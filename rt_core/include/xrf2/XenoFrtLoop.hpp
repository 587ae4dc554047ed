// XenoFrtLoop — XRF2's periodic firm real-time loop. Deadlines lie on a fixed grid t0 + k*T; a
// cycle that ends after the next deadline counts as missed, the next cycle then starts at once,
// and the grid never shifts.
#pragma once

#include <cstdint>

#include "xrf_evl_compat.h"

class XenoFrtLoop {
public:
    explicit XenoFrtLoop(unsigned cycle_time_freq);
    virtual ~XenoFrtLoop() = default;
    XenoFrtLoop(const XenoFrtLoop &) = delete;
    XenoFrtLoop &operator=(const XenoFrtLoop &) = delete;

    // One cycle; a non-zero return ends the loop.
    virtual int step() = 0;
    // Runs until step() returns non-zero (or a stop signal), then prints run time, cycles and
    // missed cycles. Returns 0, or a negative errno when the loop could not start.
    int loop();

    unsigned long getCyclesCount() const;
    unsigned long getMissedCycles() const;
    // Total time slept between cycles, in nanoseconds.
    long long getIdleTime() const;
    unsigned getCycleFrequency() const { return xrf_cycle_freq_; }

protected:
    // Called on the loop thread after the last cycle, whatever ended the loop.
    virtual void xrfAfterLastCycle() {}

private:
    unsigned xrf_cycle_freq_;
};
