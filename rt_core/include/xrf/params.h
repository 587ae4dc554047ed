/*
 * xrf/params.h — live parameter tuning: the parameter block of a run's shared memory (a field of
 * struct xrf_shm, channels.h) and its operations. The one definition for the loop (runtime.cpp)
 * and, through cffi, for the host (appliance/xrflab/channels/params.py).
 *
 * Who writes what:
 *  - the table (count, desc[]): the loop, once, before it sets xrf_shm.ready. It lists every
 *    parameter the controller declared (xrf/tunable.hpp) or the build found in a 20-sim export.
 *  - the request (req_*): one host writer (the appliance serialises its own sets) under a
 *    seqlock: req_seq odd while the host writes; each even value is a new set.
 *  - the answer (ack_*, value[]): the loop, when it has taken a set at a cycle boundary, before
 *    the controller computes: ack_seq = the request's seq, ack_cycle = the cycle it applied at.
 *
 * The loop's side is a bounded copy: one acquire load per cycle when nothing is pending, no
 * allocation, no syscall, no lock a host can hold (a set the host is still writing is taken one
 * cycle later). The whole block is also written by the guest: the host reads the table once
 * through xrf_params_table_read, which bounds the count and checks every name and number, and
 * trusts nothing else of the answer but equality of ack_seq and a bounded result code.
 */
#ifndef XRF_PARAMS_H
#define XRF_PARAMS_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* cffi-begin */
#define XRF_PARAMS_MAX 64     /* parameters one controller has */
#define XRF_PARAM_SET_MAX 64  /* entries in one set (every parameter at once) */
#define XRF_PARAM_NAME_MAX 64 /* including the NUL */
#define XRF_PARAM_UNIT_MAX 16 /* including the NUL */

/* Where a parameter lives in the controller (xrf_param_desc.source). */
#define XRF_PARAM_SOURCE_DECLARED 1 /* an XRF_TUNABLE of xrf/tunable.hpp */
#define XRF_PARAM_SOURCE_20SIM 2    /* m_P[index] of the 20-sim submodel */

/* xrf_param_desc.flags */
#define XRF_PARAM_HAS_RANGE 1 /* min..max were declared; else the host proposes one */

/* xrf_params.origin: what the table was made from, so a host can say why it is empty. */
#define XRF_PARAMS_ORIGIN_NONE 0  /* nothing declared */
#define XRF_PARAMS_ORIGIN_20SIM 1 /* a 20-sim export (maybe 0 parameters: inlined constants) */

struct xrf_param_desc {
    char name[XRF_PARAM_NAME_MAX]; /* e.g. "PID_Left\\Kp" (20-sim's own spelling) */
    char unit[XRF_PARAM_UNIT_MAX];
    double initial; /* the value the controller starts with (its default) */
    double min;
    double max;
    uint32_t source; /* XRF_PARAM_SOURCE_* */
    uint32_t flags;  /* XRF_PARAM_HAS_RANGE */
};

struct xrf_params {
    /* table: the loop, before ready */
    uint32_t count;  /* entries of desc in use */
    uint32_t origin; /* XRF_PARAMS_ORIGIN_* */
    struct xrf_param_desc desc[XRF_PARAMS_MAX];

    /* request: host -> loop, seqlock on req_seq */
    uint32_t req_seq;
    uint32_t req_count;
    uint32_t req_index[XRF_PARAM_SET_MAX]; /* indices into desc */
    double req_value[XRF_PARAM_SET_MAX];

    /* answer: loop -> host; ack_seq is stored last */
    uint32_t ack_seq;
    int32_t
        ack_result; /* 0 applied; -EINVAL nothing applied (an index or value the loop refused) */
    uint64_t ack_cycle; /* the cycle (xrf_status.cycles numbering) the set was applied at */
    double value[XRF_PARAMS_MAX]; /* every parameter's value after the last applied set */
};

/* A set as the loop copied it out of the segment (the loop's own memory). */
struct xrf_param_set {
    uint32_t seq;
    uint32_t count;
    uint32_t index[XRF_PARAM_SET_MAX];
    double value[XRF_PARAM_SET_MAX];
};

/* Host: writes a set of n entries (1 .. XRF_PARAM_SET_MAX) and returns its seq (> 0, even);
 * -EINVAL for a bad n or a non-finite value, -EBUSY when the block is held by a writer that does
 * not finish (another host, or the guest). Indices are checked against the table by the caller
 * (the host's own copy of it); the loop checks them again. */
int64_t xrf_params_request(struct xrf_params *p, const uint32_t *index, const double *value,
                           uint32_t n);
/* Host: 1 when the loop has answered request `seq` (its result into *result, clamped to 0 or
 * -EINVAL, and its cycle into *cycle), 0 not yet. */
int xrf_params_answered(const struct xrf_params *p, uint32_t seq, int32_t *result, uint64_t *cycle);
/* Host: the table, copied once into out (its own memory) and checked: count <= XRF_PARAMS_MAX,
 * every name non-empty, NUL-terminated and printable ASCII without quotes, every unit
 * NUL-terminated and printable, initial/min/max finite with min <= initial <= max, a known source.
 * Returns the count, or -EPROTO (out then holds nothing usable). */
int xrf_params_table_read(const struct xrf_params *p, struct xrf_params *out);
/* Host: the loop's current values, each copied once; a non-finite one becomes the default. */
void xrf_params_values_read(const struct xrf_params *p, const struct xrf_params *table,
                            double *out);

/* Loop: 1 when a complete set newer than *seen was copied into *out (and *seen moved on),
 * 0 when nothing new or a host is writing (taken next cycle). The caller checks the entries
 * (xrf_params_set_check) and answers with xrf_params_answer. */
int xrf_params_take(struct xrf_params *p, uint32_t *seen, struct xrf_param_set *out);
/* Loop: 0 when every index < count and every value finite, else -EINVAL. */
int xrf_params_set_check(const struct xrf_param_set *s, uint32_t count);
/* Loop: publishes the answer to request seq (ack_seq last). */
void xrf_params_answer(struct xrf_params *p, uint32_t seq, int32_t result, uint64_t cycle);
/* cffi-end */

#ifdef __cplusplus
}
#endif

#endif /* XRF_PARAMS_H */
