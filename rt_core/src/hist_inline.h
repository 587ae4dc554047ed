/*
 * hist_inline.h — the one definition of a histogram update (xrf_hist in channels.h), as static
 * inline functions. channels.c exports them as xrf_hist_bucket/xrf_hist_add (the hosts' and the
 * tests' entry points); the runtime includes this header so that the eight updates of every
 * cycle are inlined: as calls into channels.c they were a fifth of the loop's framework
 * instructions (bench/rt_core/README.md, issue 30).
 */
#ifndef XRF_HIST_INLINE_H
#define XRF_HIST_INLINE_H

#include <stdint.h>

#include "xrf/channels.h"

#define XRF_HIST_SUB (1 << XRF_HIST_SUB_BITS)
#define XRF_HIST_LINEAR (2 * XRF_HIST_SUB) /* below this, one bucket per nanosecond */
/* From 2^XRF_HIST_TOP_E ns on, every value is in the last bucket: octave e holds buckets
 * LINEAR + (e - SUB_BITS - 1) * SUB .. + SUB - 1, so the last whole octave ends at BUCKETS - 1. */
#define XRF_HIST_TOP_E ((XRF_HIST_BUCKETS - XRF_HIST_LINEAR) / XRF_HIST_SUB + XRF_HIST_SUB_BITS + 1)
#if (XRF_HIST_BUCKETS - XRF_HIST_LINEAR) % XRF_HIST_SUB != 0 || XRF_HIST_TOP_E > 63
#error "xrf_hist: the log-linear buckets must end with a whole octave below 2^63 ns"
#endif

static inline int xrf_hist_bucket_inline(uint64_t ns)
{
    /* One unsigned compare for the usual case, LINEAR <= ns < 2^TOP_E: no clamp needed there. */
    if (__builtin_expect(ns - XRF_HIST_LINEAR < ((uint64_t)1 << XRF_HIST_TOP_E) - XRF_HIST_LINEAR,
                         1)) {
        const int e = 63 - __builtin_clzll(ns); /* >= XRF_HIST_SUB_BITS + 1 */
        /* The top XRF_HIST_SUB_BITS + 1 bits, SUB + sub, give the sub-bucket with the octave's
         * offset folded in: LINEAR + (e - SUB_BITS - 1) * SUB + sub in two operations. */
        const int top = (int)(ns >> (e - XRF_HIST_SUB_BITS)); /* XRF_HIST_SUB + sub */
        return XRF_HIST_LINEAR + (e - XRF_HIST_SUB_BITS - 2) * XRF_HIST_SUB + top;
    }
    return ns < XRF_HIST_LINEAR ? (int)ns : XRF_HIST_BUCKETS - 1;
}

static inline void xrf_hist_add_inline(struct xrf_hist *h, uint64_t ns)
{
    h->count++;
    h->sum_ns += ns;
    /* Branches, not conditional stores: a new extreme is rare, so they are predicted. */
    if (ns < h->min_ns)
        h->min_ns = ns;
    if (ns > h->max_ns)
        h->max_ns = ns;
    h->buckets[xrf_hist_bucket_inline(ns)]++;
}

#endif
