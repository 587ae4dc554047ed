// XenoFrtLoop — XRF2's periodic firm real-time loop. Deadlines lie on a fixed grid t0 + k*T that
// never shifts. A cycle that wakes or ends after the next period has begun has lost that period
// (and any other begun meanwhile): the next cycle starts at the first boundary still ahead, and
// the periods passed over count as missed (docs/rt_core/runtime.md, "After an overrun").
#pragma once

#include <cstdint>
#include <error.h>
#include <time.h>

#include "FullStateMachine.hpp"
#include "debug_settings.h"
#include "xrf_evl_compat.h"

// XRF2's macros (nanoseconds in a millisecond / a second), same definitions.
#define MSEC 1000000L
#define SEC 1000000000L

class XenoFrtLoop
{
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

    // XRF2's types: completed cycles, missed cycles (periods in which no cycle started; int), and
    // the time the last idle period began (the end of the previous cycle's work) on the loop's
    // monotonic clock.
    int getCyclesCount() const;
    int getMissedCycles() const;
    struct timespec getIdleTime() const { return idle_time; }
    unsigned getCycleFrequency() const { return xrf_cycle_freq_; }

protected:
    // Called on the loop thread after the last cycle, whatever ended the loop.
    virtual void xrfAfterLastCycle() {}

    // XRF2's protected members, with XRF2's meaning, kept up to date by loop() from the
    // timestamps it takes anyway (no extra clock reads). All on the loop's monotonic clock
    // (evl_read_clock(EVL_CLOCK_MONOTONIC, ...) reads the same one).
    unsigned cycle_time_freq; // the cycle frequency in Hz (after an XRF_FREQ override)
    struct timespec start_time {
    }; // when the loop started (the grid's t0)
    struct timespec stop_time {
    }; // when it ended
    struct timespec idle_time {
    }; // when the last idle period began (end of the last cycle's work)
    struct timespec wakeup_time {
    }; // the current cycle's deadline on the grid (its start)
    struct timespec run_time {
    }; // stop_time - start_time, set when the loop ends

private:
    unsigned xrf_cycle_freq_;
};
