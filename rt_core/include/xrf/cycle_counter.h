/*
 * xrf/cycle_counter.h — the CPU's own constant-rate counter, for the stage boundaries inside one
 * cycle (issue 30 item 5). Six stage timestamps a cycle through clock_gettime were a tenth of
 * the loop's framework instructions; the counter is what the vDSO reads underneath, without
 * its seqlock, its conversion to a timespec and the call.
 *
 * Only durations inside a cycle come from it: the cycle's wake-up, its end, the deadline-miss
 * decision and every timestamp a host sees stay on the loop's clock (Runtime::now()). The rate
 * is measured against CLOCK_MONOTONIC before the loop runs (Runtime::enter), so an error of the
 * measurement scales a stage time (10^-5 over 2 ms: 0.1 ns of a 10 µs stage), never a deadline.
 *
 * aarch64: CNTVCT_EL0, the generic timer's virtual count (54 MHz on a Pi 4: 18.5 ns, the same
 * resolution CLOCK_MONOTONIC has there, since Linux's clocksource is this counter). Linux lets
 * EL0 read it; the ISB keeps the read after the instructions of the stage it closes, as the
 * kernel's vDSO does.
 * x86-64: RDTSC after an LFENCE (the vDSO's rdtsc_ordered), used only when CPUID says the TSC
 * is invariant (constant rate, runs in every C-state and P-state).
 * Elsewhere: no counter (0), and the runtime reads its clock instead.
 */
#ifndef XRF_CYCLE_COUNTER_H
#define XRF_CYCLE_COUNTER_H

#include <stdint.h>

#if defined(__x86_64__)
#include <cpuid.h>
#include <x86intrin.h>
#endif

/* 1 if this build reads a counter at all (the runtime still checks it is usable). */
#if defined(__x86_64__) || defined(__aarch64__)
#define XRF_HAVE_CYCLE_COUNTER 1
#else
#define XRF_HAVE_CYCLE_COUNTER 0
#endif

static inline uint64_t xrf_cycle_counter(void)
{
#if defined(__aarch64__)
    uint64_t v;
    __asm__ __volatile__("isb\n\tmrs %0, cntvct_el0" : "=r"(v)::"memory");
    return v;
#elif defined(__x86_64__)
    _mm_lfence();
    return __rdtsc();
#else
    return 0;
#endif
}

/* Whether the counter runs at one rate whatever the CPU does (checked once, in-band). */
static inline int xrf_cycle_counter_invariant(void)
{
#if defined(__aarch64__)
    return 1; /* the generic timer's rate is fixed by the architecture */
#elif defined(__x86_64__)
    unsigned a, b, c, d;
    if (!__get_cpuid(0x80000000u, &a, &b, &c, &d) || a < 0x80000007u)
        return 0;
    __get_cpuid(0x80000007u, &a, &b, &c, &d);
    return (d >> 8) & 1u; /* "invariant TSC" (Intel SDM and AMD APM: CPUID 8000_0007h EDX[8]) */
#else
    return 0;
#endif
}

/* Counter ticks to nanoseconds: mult is ns per tick in 32.32 fixed point. The 128-bit product
 * does not overflow for any tick count (one multiply-high on both architectures). */
__extension__ typedef unsigned __int128 xrf_cycle_counter_u128; /* quiet under -Wpedantic */

static inline int64_t xrf_cycle_counter_ns(uint64_t ticks, uint64_t mult)
{
    return (int64_t)(uint64_t)(((xrf_cycle_counter_u128)ticks * mult) >> 32);
}

#endif
