/*
 * channels_inline.h — the one definition of the loop's side of the per-cycle handoffs (status
 * seqlock writer, broadcast and SPSC ring producers, command poll), as static inline functions.
 * channels.c exports them under their xrf/channels.h names (the hosts', the binding's and the
 * tests' entry points); the runtime includes this header so that the five handoffs of every
 * cycle are inlined: as calls into channels.c they cost a call, spills and reloads each
 * (bench/rt_core/README.md, issue 30 item 5). The memory orderings are channels.c's own, stated
 * once here; docs/rt_core/memory-order.md has the table, tests/rt_core/test_tsan.py checks them.
 * Compiles as C and as C++ (the runtime is C++).
 */
#ifndef XRF_CHANNELS_INLINE_H
#define XRF_CHANNELS_INLINE_H

#include <stdint.h>

#include "xrf/channels.h"

#define XRF_LOAD_ACQ(p) __atomic_load_n((p), __ATOMIC_ACQUIRE)
#define XRF_LOAD_RLX(p) __atomic_load_n((p), __ATOMIC_RELAXED)
#define XRF_STORE_REL(p, v) __atomic_store_n((p), (v), __ATOMIC_RELEASE)
#define XRF_STORE_RLX(p, v) __atomic_store_n((p), (v), __ATOMIC_RELAXED)

/* ---- status seqlock, writer ---------------------------------------------------------------- */

/* Writer (the loop only, so its own seq is read back RELAXED): odd, then a RELEASE fence so no
 * store of the block becomes visible before the odd value (a reader seeing a new field then sees
 * seq changed); even with RELEASE after the last store of the block. */
static inline void xrf_status_write_begin_inline(struct xrf_status *s)
{
    XRF_STORE_RLX(&s->seq, XRF_LOAD_RLX(&s->seq) + 1);
    __atomic_thread_fence(__ATOMIC_RELEASE); /* odd seq visible before any data store */
}

static inline void xrf_status_write_end_inline(struct xrf_status *s)
{
    XRF_STORE_REL(&s->seq, XRF_LOAD_RLX(&s->seq) + 1);
}

/* ---- commands: the consumer of the Vyukov queue --------------------------------------------- */

static inline int xrf_cmd_poll_inline(struct xrf_cmd_ring *r, struct xrf_cmd_slot *out)
{
    /* tail: the loop's own word (RELAXED). The slot's seq with ACQUIRE: pos + 1 means a sender's
     * RELEASE published its fields, which the copy then reads. Handing the slot back is a RELEASE
     * of seq after the copy, so a sender that sees it free cannot overwrite what is being read. */
    uint64_t pos = XRF_LOAD_RLX(&r->tail);
    struct xrf_cmd_slot *slot = &r->slot[pos & (XRF_CMD_SLOTS - 1)];
    if (XRF_LOAD_ACQ(&slot->seq) != pos + 1)
        return 0;
    *out = *slot;
    XRF_STORE_REL(&slot->seq, pos + XRF_CMD_SLOTS);
    XRF_STORE_REL(&r->tail, pos + 1);
    return 1;
}

/* ---- rings of fixed-size slots, producer --------------------------------------------------- */

/* The producer's view of its own ring: geometry it set itself (RELAXED: readers only compare it). */
static inline struct xrf_slot_hdr *xrf_slot_at_inline(const struct xrf_ring *r, const void *slots,
                                                      uint64_t n)
{
    return (struct xrf_slot_hdr *)((uint8_t *)(uintptr_t)slots +
                                   (size_t)(n & (XRF_LOAD_RLX(&r->slots) - 1)) *
                                       XRF_LOAD_RLX(&r->slot_size));
}

/* Broadcast: a seqlock per slot. seq = 2n+1 (RELAXED) then a RELEASE fence: no store of the
 * payload becomes visible before it. The producer fills the slot; commit stores 2n+2 with
 * RELEASE (the payload is before it), then head with RELEASE (the slot is before it). A reader
 * loads head ACQUIRE, the slot's seq ACQUIRE, copies (xrf_seq_copy), fence ACQUIRE, seq again. */
static inline void *xrf_bcast_begin_inline(struct xrf_ring *r, void *slots)
{
    uint64_t n = XRF_LOAD_RLX(&r->head); /* the producer's own word */
    struct xrf_slot_hdr *slot = xrf_slot_at_inline(r, slots, n);
    XRF_STORE_RLX(&slot->seq, 2 * n + 1);
    __atomic_thread_fence(__ATOMIC_RELEASE);
    return slot;
}

static inline void xrf_bcast_commit_inline(struct xrf_ring *r, void *slot)
{
    uint64_t n = XRF_LOAD_RLX(&r->head);
    XRF_STORE_REL(&((struct xrf_slot_hdr *)slot)->seq, 2 * n + 2);
    XRF_STORE_REL(&r->head, n + 1);
}

/* SPSC (the log): tail ACQUIRE -- the consumer's RELEASE of tail came after it finished reading
 * the slots it gave back, so the producer's next stores into them cannot reach the consumer's
 * reads. head: the producer's own word, RELAXED; published with RELEASE after the record. */
static inline void *xrf_spsc_begin_inline(struct xrf_ring *r, void *slots)
{
    uint64_t head = XRF_LOAD_RLX(&r->head);
    if (head - XRF_LOAD_ACQ(&r->tail) >= XRF_LOAD_RLX(&r->slots)) {
        XRF_STORE_RLX(&r->dropped, XRF_LOAD_RLX(&r->dropped) + 1);
        return NULL;
    }
    return xrf_slot_at_inline(r, slots, head);
}

static inline void xrf_spsc_commit_inline(struct xrf_ring *r, void *slot)
{
    (void)slot;
    XRF_STORE_REL(&r->head, XRF_LOAD_RLX(&r->head) + 1);
}

#endif
