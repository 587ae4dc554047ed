// XenoFrtMonitor: decimated printing into the monitor ring.
#include "XenoFrtMonitor.hpp"

#include <cstdarg>

#include "xrf/runtime.hpp"

XenoFrtMonitor::XenoFrtMonitor(unsigned cycle_freq, unsigned monitor_freq)
{
    // round(cycle / monitor); 0 means off rather than a division by zero (an XRF2 defect).
    divider_ = monitor_freq == 0 ? 0 : (cycle_freq + monitor_freq / 2) / monitor_freq;
    if (monitor_freq != 0 && divider_ == 0)
        divider_ = 1;
}

void XenoFrtMonitor::printf(const char *fmt, ...)
{
    if (!due_)
        return;
    va_list ap;
    va_start(ap, fmt);
    xrf::Runtime::instance().monitorWrite(fmt, ap);
    va_end(ap);
}
