/*
 * The parameter block of xrf/params.h. Compiled into the runtime library and, unchanged, into the
 * Python binding: the loop and the host use the same code.
 *
 * The loop's side (xrf_params_take, _set_check, _answer) is a bounded copy: no allocation, no
 * lock, no system call. Everything read from the block by the host is bounded: the guest writes it.
 */
#include "xrf/params.h"

#include <errno.h>
#include <math.h>
#include <string.h>

#define LOAD_ACQ(p) __atomic_load_n((p), __ATOMIC_ACQUIRE)
#define LOAD_RLX(p) __atomic_load_n((p), __ATOMIC_RELAXED)
#define STORE_REL(p, v) __atomic_store_n((p), (v), __ATOMIC_RELEASE)
#define STORE_RLX(p, v) __atomic_store_n((p), (v), __ATOMIC_RELAXED)

/* How many times a host tries to claim a block another writer holds. */
#define XRF_PARAMS_CLAIM_TRIES 1000

_Static_assert(sizeof(struct xrf_param_desc) % 8 == 0, "param desc must keep 8-byte alignment");
_Static_assert(sizeof(struct xrf_params) % 8 == 0, "param block must keep 8-byte alignment");

int64_t xrf_params_request(struct xrf_params *p, const uint32_t *index, const double *value,
                           uint32_t n)
{
    if (p == NULL || index == NULL || value == NULL || n == 0 || n > XRF_PARAM_SET_MAX)
        return -EINVAL;
    for (uint32_t i = 0; i < n; i++)
        if (!isfinite(value[i]))
            return -EINVAL;
    uint32_t seq = 0;
    int claimed = 0;
    for (int t = 0; t < XRF_PARAMS_CLAIM_TRIES && !claimed; t++) {
        seq = LOAD_RLX(&p->req_seq);
        if (seq & 1u)
            continue;
        claimed = __atomic_compare_exchange_n(&p->req_seq, &seq, seq + 1u, 0, __ATOMIC_ACQ_REL,
                                              __ATOMIC_RELAXED);
    }
    if (!claimed)
        return -EBUSY;
    /* seq + 2 is even and never 0 again for 2^31 sets: 0 means "no set yet" to the loop. */
    uint32_t next = seq + 2u;
    if (next == 0)
        next = 2;
    STORE_RLX(&p->req_count, n);
    for (uint32_t i = 0; i < n; i++) {
        double v = value[i];
        STORE_RLX(&p->req_index[i], index[i]);
        __atomic_store(&p->req_value[i], &v, __ATOMIC_RELAXED);
    }
    STORE_REL(&p->req_seq, next);
    return next;
}

int xrf_params_answered(const struct xrf_params *p, uint32_t seq, int32_t *result, uint64_t *cycle)
{
    if (LOAD_ACQ(&p->ack_seq) != seq)
        return 0;
    int32_t r = LOAD_RLX(&p->ack_result);
    uint64_t c = LOAD_RLX(&p->ack_cycle);
    /* The answer may have moved on to a later request while we read: then it is not ours. */
    if (LOAD_ACQ(&p->ack_seq) != seq)
        return 0;
    if (result)
        *result = r == 0 ? 0 : -EINVAL;
    if (cycle)
        *cycle = c;
    return 1;
}

/* A name or unit field: NUL within the field, printable ASCII, no quote (it ends up in CSV,
 * JSON and ROS names). `nonempty`: a name must have one character at least. */
static int text_ok(const char *field, size_t size, int nonempty)
{
    size_t n = 0;
    while (n < size && field[n] != '\0') {
        unsigned char c = (unsigned char)field[n];
        if (c < 0x20 || c > 0x7e || c == '"' || c == '\'')
            return 0;
        n++;
    }
    return n < size && (!nonempty || n > 0);
}

int xrf_params_table_read(const struct xrf_params *p, struct xrf_params *out)
{
    /* One copy of the table: every check below is on the copy, which the guest cannot change. */
    memcpy(out, p, sizeof *out);
    if (out->count > XRF_PARAMS_MAX || out->origin > XRF_PARAMS_ORIGIN_20SIM)
        goto bad;
    for (uint32_t i = 0; i < out->count; i++) {
        const struct xrf_param_desc *d = &out->desc[i];
        if (!text_ok(d->name, sizeof d->name, 1) || !text_ok(d->unit, sizeof d->unit, 0))
            goto bad;
        if (!isfinite(d->initial) || !isfinite(d->min) || !isfinite(d->max) ||
            d->min > d->initial || d->initial > d->max)
            goto bad;
        if (d->source != XRF_PARAM_SOURCE_DECLARED && d->source != XRF_PARAM_SOURCE_20SIM)
            goto bad;
        for (uint32_t j = 0; j < i; j++)
            if (strcmp(out->desc[j].name, d->name) == 0)
                goto bad;
    }
    return (int)out->count;
bad:
    memset(out, 0, sizeof *out);
    return -EPROTO;
}

void xrf_params_values_read(const struct xrf_params *p, const struct xrf_params *table, double *out)
{
    uint32_t n = table->count <= XRF_PARAMS_MAX ? table->count : XRF_PARAMS_MAX;
    for (uint32_t i = 0; i < n; i++) {
        double v;
        __atomic_load(&p->value[i], &v, __ATOMIC_RELAXED);
        out[i] = isfinite(v) ? v : table->desc[i].initial;
    }
}

int xrf_params_take(struct xrf_params *p, uint32_t *seen, struct xrf_param_set *out)
{
    const uint32_t seq = LOAD_ACQ(&p->req_seq);
    if (seq == *seen || (seq & 1u))
        return 0;
    uint32_t n = LOAD_RLX(&p->req_count);
    if (n > XRF_PARAM_SET_MAX)
        n = XRF_PARAM_SET_MAX + 1u; /* kept out of range: set_check refuses the set */
    const uint32_t copy = n <= XRF_PARAM_SET_MAX ? n : XRF_PARAM_SET_MAX;
    for (uint32_t i = 0; i < copy; i++) {
        out->index[i] = LOAD_RLX(&p->req_index[i]);
        __atomic_load(&p->req_value[i], &out->value[i], __ATOMIC_RELAXED);
    }
    __atomic_thread_fence(__ATOMIC_ACQUIRE);
    if (LOAD_RLX(&p->req_seq) != seq)
        return 0; /* a host wrote meanwhile: the next cycle takes the finished set */
    out->seq = seq;
    out->count = n;
    *seen = seq;
    return 1;
}

int xrf_params_set_check(const struct xrf_param_set *s, uint32_t count)
{
    if (s->count == 0 || s->count > XRF_PARAM_SET_MAX)
        return -EINVAL;
    for (uint32_t i = 0; i < s->count; i++)
        if (s->index[i] >= count || !isfinite(s->value[i]))
            return -EINVAL;
    return 0;
}

void xrf_params_answer(struct xrf_params *p, uint32_t seq, int32_t result, uint64_t cycle)
{
    STORE_RLX(&p->ack_result, result);
    STORE_RLX(&p->ack_cycle, cycle);
    STORE_REL(&p->ack_seq, seq);
}
