// Times xrf::Runtime::endCycle() — the per-cycle status seqlock, histogram updates and doorbell
// check — which no stage histogram covers. Uses the runtime's own enter()/endCycle()/leave() on a
// real shared-memory object (XRF_SHM), N calls back to back on the calling thread (hot caches:
// a lower bound of the in-loop cost). Prints "endcycle_ns_mean <x>".
#include <cstdio>
#include <cstdlib>
#include <ctime>

#include "xrf/runtime.hpp"

static int64_t nowNs()
{
    timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

int main(int argc, char **argv)
{
    const long n = argc > 1 ? std::atol(argv[1]) : 1000000;
    xrf::Runtime &rt = xrf::Runtime::instance();
    if (rt.enter(1000) != 0)
        return 1;
    // Like a cycle in RUN: all six stages set, as XenoFrtRosIcoCore::step() leaves them.
    int64_t t = rt.now();
    const int64_t t0 = nowNs();
    for (long i = 0; i < n; i++) {
        for (int s = XRF_STAGE_FPGA; s <= XRF_STAGE_LOGGER; s++)
            rt.stage(s, 1000 + (i & 1023));
        rt.endCycle(t, t - 2000 - (i & 4095), t + 5000, 0, 900000);
        t += 1000000;
    }
    const int64_t t1 = nowNs();
    rt.leave();
    std::printf("endcycle_calls %ld\nendcycle_ns_mean %.1f\n", n, (double)(t1 - t0) / (double)n);
    return 0;
}
