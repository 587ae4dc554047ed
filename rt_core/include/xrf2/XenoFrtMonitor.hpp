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
    void update();
    void printf(const char *fmt, ...) __attribute__((format(printf, 2, 3)));
    bool isDue() const { return due_; }

private:
    unsigned divider_;
    unsigned phase_ = 0; // cycles since the last due one, 0..divider_-1 (no division per cycle)
    bool due_ = false;
};
