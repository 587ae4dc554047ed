// XenoFrtMonitor — rate-limited printf: prints only on every round(cycle_freq / monitor_freq)-th
// cycle; monitor_freq 0 silences it. Text goes into the monitor ring; it never blocks the loop.
#pragma once

#include <stdarg.h>
#include <stdio.h>

#include "xrf_evl_compat.h"

#ifndef MSEC
#define MSEC 1000000L
#endif
#ifndef SEC
#define SEC 1000000000L
#endif

class XenoFrtMonitor
{
public:
    XenoFrtMonitor(unsigned cycle_freq, unsigned monitor_freq);
    // Once per cycle, before the hook. Due on cycles 0, divider_, 2 divider_, ...: a count-down
    // instead of a modulo, inline because the loop calls it every cycle (issue 30 item 5).
    void update()
    {
        due_ = divider_ != 0 && phase_ == 0;
        if (++phase_ >= divider_)
            phase_ = 0;
    }
    void printf(const char *fmt, ...) __attribute__((format(printf, 2, 3)));
    bool isDue() const { return due_; }

private:
    unsigned divider_;
    unsigned phase_ = 0; // cycles since the last due one, 0..divider_-1 (no division per cycle)
    bool due_ = false;
};
