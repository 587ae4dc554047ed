/*
 * The channel operations of xrf/channels.h. Compiled into the runtime library and, unchanged,
 * into the Python binding, so the loop and every host use the very same code.
 *
 * Nothing on the loop's side of these functions allocates, locks or makes a system call, except
 * xrf_doorbell_wake(), which the engine calls at most once per doorbell period and only when a
 * host is waiting.
 */
#define _GNU_SOURCE
#include "xrf/channels.h"
#include "xrf/logformat.h"   /* the type codes of the timing records */
#include "hist_inline.h"     /* the histogram update, shared with the runtime */
#include "channels_inline.h" /* the loop's side of the per-cycle handoffs, shared likewise */

#include <errno.h>
#include <limits.h>
#include <linux/futex.h>
#include <stdio.h>
#include <string.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>

/*
 * Memory ordering (issue 30: a Pi's Cortex-A72 reorders what x86 does not). Every word two sides
 * share is read and written through the __atomic builtins below, never by a plain access: a plain
 * load of an index may be torn, hoisted out of a loop or reordered around the data it guards.
 * The rule for each handoff, with its reasoning, is next to its code; docs/rt_core/memory-order.md
 * has the table, and tests/rt_core/test_tsan.py runs the two-thread stress test of every handoff
 * under ThreadSanitizer.
 *  - publish (head, ready, seq even): the data is written first, the word last with RELEASE; the
 *    reader loads the word with ACQUIRE before touching the data it covers.
 *  - own words (the producer's head, the consumer's tail, read back by their only writer):
 *    RELAXED loads; no other thread writes them, the atomic only keeps the access whole.
 *  - seqlock payloads: copied with RELAXED atomic word loads (xrf_seq_copy), validated by the
 *    sequence word after an ACQUIRE fence -- the C11 seqlock (Boehm, "Can seqlocks get along with
 *    programming language memory models?", 2012). A torn copy is thrown away, never used.
 *  - doorbell: SEQ_CST on both sides (a store then a load of the other word, which acquire/release
 *    does not order).
 */
#define LOAD_ACQ(p) XRF_LOAD_ACQ(p) /* channels_inline.h */
#define LOAD_RLX(p) XRF_LOAD_RLX(p)
#define STORE_REL(p, v) XRF_STORE_REL(p, v)
#define STORE_RLX(p, v) XRF_STORE_RLX(p, v)

/* A seqlock reader's copy of `n` bytes its writer may be changing: relaxed atomic loads, word by
 * word where both pointers allow it (every payload here is 8-byte aligned), so the racing access
 * is defined behaviour in C11 (a memcpy racing with a store is not) and ThreadSanitizer sees an
 * atomic read. On arm64 and x86 a relaxed 8-byte load is the plain `ldr`/`mov` memcpy would use:
 * the copy costs no barrier; the caller's acquire fence orders it before the re-check. */
static void xrf_seq_copy(void *dst, const void *src, size_t n)
{
    uint8_t *d = dst;
    const uint8_t *s = src;
    if ((((uintptr_t)d | (uintptr_t)s) & 7u) == 0) {
        for (; n >= 8; n -= 8, d += 8, s += 8) {
            uint64_t w = __atomic_load_n((const uint64_t *)(const void *)s, __ATOMIC_RELAXED);
            memcpy(d, &w, 8);
        }
    }
    for (; n > 0; n--)
        *d++ = __atomic_load_n(s++, __ATOMIC_RELAXED);
}

/* The writer's half, for a writer in this file (the Ros2Xeno buffer): relaxed atomic stores
 * between the odd and the even sequence word. */
static void xrf_seq_store(void *dst, const void *src, size_t n)
{
    uint8_t *d = dst;
    const uint8_t *s = src;
    if ((((uintptr_t)d | (uintptr_t)s) & 7u) == 0) {
        for (; n >= 8; n -= 8, d += 8, s += 8) {
            uint64_t w;
            memcpy(&w, s, 8);
            __atomic_store_n((uint64_t *)(void *)d, w, __ATOMIC_RELAXED);
        }
    }
    for (; n > 0; n--)
        __atomic_store_n(d++, *s++, __ATOMIC_RELAXED);
}

/* How often a reader retries a slot that a (possibly dead) writer holds before giving up. */
#define XRF_SPIN_LIMIT 100000
/* Tries of one status read: each may copy the whole block (~33 KiB), so a loop that flips its
 * seq all the time holds a reader for a fraction of a millisecond (64 tries, ~2 MiB copied).
 * The caller retries for a bounded time, sleeping in between: a real loop holds the lock for
 * about a microsecond once a cycle, but may be descheduled while it does (valgrind, a busy
 * host without real time). */
#define XRF_STATUS_TRIES 64
/* Largest ring a reader accepts: counts stay within an int, offsets within 64 bits. */
#define XRF_RING_SLOTS_MAX (1u << 30)

_Static_assert(sizeof(struct xrf_telemetry) % 8 == 0, "telemetry slot must keep 8-byte alignment");
_Static_assert(sizeof(struct xrf_monitor_line) % 8 == 0, "monitor slot must keep 8-byte alignment");
_Static_assert((XRF_CMD_SLOTS & (XRF_CMD_SLOTS - 1)) == 0, "command slots: power of two");
_Static_assert((XRF_TELEM_SLOTS & (XRF_TELEM_SLOTS - 1)) == 0, "telemetry slots: power of two");
_Static_assert((XRF_MONITOR_SLOTS & (XRF_MONITOR_SLOTS - 1)) == 0, "monitor slots: power of two");
_Static_assert(offsetof(struct xrf_shm, log_data) % 8 == 0, "log data must be 8-byte aligned");
_Static_assert(sizeof(struct xrf_timing_record) % 8 == 0, "timing slot must keep 8-byte alignment");
_Static_assert((XRF_TIMING_SLOTS & (XRF_TIMING_SLOTS - 1)) == 0, "timing slots: power of two");

_Static_assert(XRF_MAX_CHANNELS == XRF_MAX_BOARDS * XRF_ICO_CHANNELS,
               "a bench's channels are whole ico boards");

void xrf_shm_init(struct xrf_shm *shm)
{
    /* The caller hands over zeroed memory (a fresh ftruncate'd object). */
    shm->magic = XRF_SHM_MAGIC;
    shm->version = XRF_SHM_VERSION;
    shm->size = (uint32_t)sizeof(struct xrf_shm);
    /* One board until whoever knows the bench says otherwise (the runtime, from the host's
     * count or its plant's). */
    shm->channels = XRF_ICO_CHANNELS;
    shm->status.state = XRF_STATE_IDLE;
    for (int i = 0; i < XRF_STAGE_COUNT; i++)
        shm->status.hist[i].min_ns = UINT64_MAX;
    for (uint32_t i = 0; i < XRF_CMD_SLOTS; i++)
        shm->cmd.slot[i].seq = i;
    xrf_ring_init(&shm->telem_ring, XRF_TELEM_SLOTS, sizeof(struct xrf_telemetry));
    xrf_ring_init(&shm->monitor_ring, XRF_MONITOR_SLOTS, sizeof(struct xrf_monitor_line));
}

void xrf_shm_publish_ready(struct xrf_shm *shm)
{
    STORE_REL(&shm->ready, 1u);
}

void xrf_timing_meta_init(struct xrf_log_meta *m, uint32_t writer, const char *path)
{
    /* Offsets in the payload, which starts after the slot header. */
    static const struct {
        const char *name;
        int32_t type;
        size_t offset;
    } vars[] = {
#define XRF_TIMING_VAR(field, type) {#field, type, offsetof(struct xrf_timing_record, field)}
        XRF_TIMING_VAR(wakeup_ns, XRF_LOG_LONG_INT),  XRF_TIMING_VAR(fpga_ns, XRF_LOG_LONG_INT),
        XRF_TIMING_VAR(data_ns, XRF_LOG_LONG_INT),    XRF_TIMING_VAR(cmd_ns, XRF_LOG_LONG_INT),
        XRF_TIMING_VAR(monitor_ns, XRF_LOG_LONG_INT), XRF_TIMING_VAR(hook_ns, XRF_LOG_LONG_INT),
        XRF_TIMING_VAR(logger_ns, XRF_LOG_LONG_INT),  XRF_TIMING_VAR(cycle_ns, XRF_LOG_LONG_INT),
        XRF_TIMING_VAR(missed, XRF_LOG_INT),
#undef XRF_TIMING_VAR
    };
    const size_t n = sizeof vars / sizeof vars[0];
    const size_t payload = sizeof(struct xrf_slot_hdr);
    for (size_t i = 0; i < n; i++) {
        strncpy(m->vars[i].name, vars[i].name, XRF_NAME_MAX - 1);
        m->vars[i].type = vars[i].type;
        m->vars[i].offset = (int32_t)(vars[i].offset - payload);
    }
    m->nvars = (uint32_t)n;
    m->record_size =
        (uint32_t)(offsetof(struct xrf_timing_record, missed) + sizeof(int32_t) - payload);
    m->writer = writer;
    m->file_mode = 0640;
    strncpy(m->path, path, XRF_PATH_MAX - 1);
    STORE_REL(&m->generation, m->generation + 1);
    STORE_REL(&m->ready, 1u);
}

/* ---- histograms ---------------------------------------------------------------------------- */

int xrf_hist_bucket(uint64_t ns)
{
    return xrf_hist_bucket_inline(ns);
}

uint64_t xrf_hist_bucket_low(int bucket)
{
    if (bucket < XRF_HIST_LINEAR)
        return (uint64_t)(bucket < 0 ? 0 : bucket);
    int e = (bucket - XRF_HIST_LINEAR) / XRF_HIST_SUB + XRF_HIST_SUB_BITS + 1;
    int sub = (bucket - XRF_HIST_LINEAR) % XRF_HIST_SUB;
    return (uint64_t)(XRF_HIST_SUB + sub) << (e - XRF_HIST_SUB_BITS);
}

void xrf_hist_add(struct xrf_hist *h, uint64_t ns)
{
    xrf_hist_add_inline(h, ns);
}

/* ---- status seqlock ------------------------------------------------------------------------ */

/* The writer (the loop): channels_inline.h, where the orderings are stated. */
void xrf_status_write_begin(struct xrf_status *s)
{
    xrf_status_write_begin_inline(s);
}

void xrf_status_write_end(struct xrf_status *s)
{
    xrf_status_write_end_inline(s);
}

int xrf_status_read(const struct xrf_status *s, struct xrf_status *out)
{
    for (int tries = 0; tries < XRF_STATUS_TRIES; tries++) {
        /* ACQUIRE: the block's stores of the write that made s1 are visible to the copy. The
         * ACQUIRE fence keeps the copy's loads before the second seq load: if any of them saw a
         * later write's store, that write's odd seq is seen here and the copy is retried. */
        uint32_t s1 = LOAD_ACQ(&s->seq);
        if (s1 & 1u)
            continue;
        xrf_seq_copy(out, s, sizeof *out);
        __atomic_thread_fence(__ATOMIC_ACQUIRE);
        if (LOAD_RLX(&s->seq) == s1)
            return 0;
    }
    return -EAGAIN;
}

/* ---- commands: bounded multi-producer queue (Vyukov), one consumer -------------------------- */

int64_t xrf_cmd_send(struct xrf_cmd_ring *r, int32_t cmd, int32_t source, int64_t t_sent_ns)
{
    uint64_t pos = LOAD_RLX(&r->head);
    struct xrf_cmd_slot *slot;
    /* head and the slot seqs are the loop's memory: a loop that sets them so that no slot ever
     * looks free-for-this-position must not keep a host here (it used to spin forever). */
    for (int tries = 0;; tries++) {
        if (tries >= XRF_SPIN_LIMIT)
            return -EBUSY;
        if (pos >= (uint64_t)INT64_MAX)
            return -EPROTO; /* no ticket (> 0 as an int64) follows this head */
        slot = &r->slot[pos & (XRF_CMD_SLOTS - 1)];
        /* The difference in uint64 (wraps, defined), then signed: both may be anything. */
        int64_t dif = (int64_t)(LOAD_ACQ(&slot->seq) - pos);
        if (dif == 0) {
            if (__atomic_compare_exchange_n(&r->head, &pos, pos + 1, 0, __ATOMIC_RELAXED,
                                            __ATOMIC_RELAXED))
                break;
        } else if (dif < 0) {
            return -EAGAIN; /* full: the loop is not consuming */
        } else {
            pos = LOAD_RLX(&r->head);
        }
    }
    /* The slot is this sender's alone from the CAS on (its seq said free for `pos`, which no
     * other sender can claim now); the ACQUIRE load of that seq ordered the consumer's last read
     * of the slot before these stores. The fields go plain, the slot's seq last with RELEASE. */
    slot->ticket = pos + 1;
    slot->cmd = cmd;
    slot->source = source;
    slot->t_sent_ns = t_sent_ns;
    STORE_REL(&slot->seq, pos + 1);
    return (int64_t)(pos + 1);
}

/* The consumer (the loop): channels_inline.h, where the orderings are stated. */
int xrf_cmd_poll(struct xrf_cmd_ring *r, struct xrf_cmd_slot *out)
{
    return xrf_cmd_poll_inline(r, out);
}

/* ---- Ros2Xeno: latest-wins seqlock buffer -------------------------------------------------- */

int xrf_data_in_write(struct xrf_data_in *d, const void *data, uint32_t size, int64_t t_sent_ns)
{
    if (size > XRF_MSG_MAX)
        return -EMSGSIZE;
    uint32_t s = 0;
    int tries = 0;
    for (;; tries++) {
        if (tries > XRF_SPIN_LIMIT)
            return -EBUSY; /* another host holds the buffer (or died holding it) */
        s = LOAD_RLX(&d->seq);
        if (s & 1u)
            continue;
        if (__atomic_compare_exchange_n(&d->seq, &s, s + 1, 0, __ATOMIC_ACQUIRE, __ATOMIC_RELAXED))
            break;
    }
    /* The CAS made seq odd (this writer's lock; ACQUIRE: the previous writer's stores are
     * before ours). The RELEASE fence keeps every store below after the odd value, as in the
     * status seqlock; the even value is the RELEASE that publishes them. The loop reads these
     * words while they change: atomic stores, never a plain memcpy. */
    __atomic_thread_fence(__ATOMIC_RELEASE);
    xrf_seq_store(d->data, data, size);
    STORE_RLX(&d->size, size);
    STORE_RLX(&d->t_sent_ns, t_sent_ns);
    STORE_RLX(&d->writes, LOAD_RLX(&d->writes) + 1);
    STORE_REL(&d->seq, s + 2);
    return 0;
}

int xrf_data_in_try_read(struct xrf_data_in *d, uint32_t *last_seq, void *out, uint32_t size,
                         int64_t *t_sent_ns)
{
    uint8_t staging[XRF_MSG_MAX];
    uint32_t s1 = LOAD_ACQ(&d->seq);
    if ((s1 & 1u) || s1 == *last_seq)
        return 0;
    if (size > XRF_MSG_MAX)
        size = XRF_MSG_MAX;
    /* The seqlock reader (see xrf_status_read): relaxed copies, ACQUIRE fence, re-check. */
    xrf_seq_copy(staging, d->data, size);
    int64_t t = LOAD_RLX(&d->t_sent_ns);
    __atomic_thread_fence(__ATOMIC_ACQUIRE);
    if (LOAD_RLX(&d->seq) != s1)
        return 0; /* torn: keep last cycle's message, take the new one next cycle */
    memcpy(out, staging, size);
    if (t_sent_ns)
        *t_sent_ns = t;
    *last_seq = s1;
    return 1;
}

/* ---- rings of fixed-size slots ------------------------------------------------------------- */

/* Before any reader attaches (xrf_shm_init) or while none reads (a logger's initialise(), whose
 * meta is not ready): the words are set RELAXED, `slots` last with RELEASE. */
void xrf_ring_init(struct xrf_ring *r, uint32_t slots, uint32_t slot_size)
{
    STORE_RLX(&r->head, 0);
    STORE_RLX(&r->tail, 0);
    STORE_RLX(&r->dropped, 0);
    STORE_RLX(&r->slot_size, slot_size);
    STORE_REL(&r->slots, slots);
}

/* The producers (the loop): channels_inline.h, where the orderings are stated. */
void *xrf_bcast_begin(struct xrf_ring *r, void *slots)
{
    return xrf_bcast_begin_inline(r, slots);
}

void xrf_bcast_commit(struct xrf_ring *r, void *slot)
{
    xrf_bcast_commit_inline(r, slot);
}

void *xrf_spsc_begin(struct xrf_ring *r, void *slots)
{
    return xrf_spsc_begin_inline(r, slots);
}

void xrf_spsc_commit(struct xrf_ring *r, void *slot)
{
    xrf_spsc_commit_inline(r, slot);
}

uint32_t xrf_log_slots_for(uint32_t record_size, uint32_t ring_bytes, uint32_t *slot_size)
{
    uint32_t ss = (uint32_t)((sizeof(struct xrf_slot_hdr) + record_size + 7u) & ~7u);
    uint32_t n = ring_bytes / ss;
    uint32_t p = 1;
    while (p * 2 <= n)
        p *= 2;
    if (slot_size)
        *slot_size = ss;
    return n ? p : 0;
}

/* ---- reading a segment: geometry in the reader's memory, every guest value bounded --------- */

int xrf_ring_geom_check(const struct xrf_ring *r, uint32_t slots, uint32_t slot_size,
                        uint64_t capacity, struct xrf_ring_geom *g)
{
    if (r == NULL || g == NULL)
        return -EINVAL;
    /* The geometry the reader expects must itself be a ring: a power of two of slots, each a
     * header and 8-byte aligned, all of them inside the space the layout gives the ring. */
    if (slots == 0 || slots > XRF_RING_SLOTS_MAX || (slots & (slots - 1)) != 0 ||
        slot_size < sizeof(struct xrf_slot_hdr) || slot_size % 8 != 0 ||
        (uint64_t)slots * slot_size > capacity)
        return -EINVAL;
    /* One read of each: what the loop says is compared, never used. */
    if (LOAD_ACQ(&r->slots) != slots || LOAD_RLX(&r->slot_size) != slot_size)
        return -EPROTO;
    g->slots = slots;
    g->slot_size = slot_size;
    return 0;
}

int xrf_shm_check(const struct xrf_shm *shm, uint64_t mapped, struct xrf_shm_geom *g)
{
    if (shm == NULL || g == NULL || mapped < sizeof(struct xrf_shm))
        return -EINVAL;
    if (LOAD_ACQ(&shm->magic) != XRF_SHM_MAGIC || LOAD_RLX(&shm->version) != XRF_SHM_VERSION ||
        LOAD_RLX(&shm->size) != sizeof(struct xrf_shm))
        return -EPROTO;
    int rc = xrf_ring_geom_check(&shm->telem_ring, XRF_TELEM_SLOTS, sizeof(struct xrf_telemetry),
                                 sizeof shm->telem, &g->telem);
    if (rc == 0)
        rc = xrf_ring_geom_check(&shm->monitor_ring, XRF_MONITOR_SLOTS,
                                 sizeof(struct xrf_monitor_line), sizeof shm->monitor, &g->monitor);
    if (rc == 0) {
        uint32_t n = LOAD_RLX(&shm->channels);
        if (n < 1 || n > XRF_MAX_CHANNELS)
            return -EPROTO;
        g->channels = n;
        g->pad = 0;
    }
    return rc;
}

uint32_t xrf_shm_channels(const struct xrf_shm *shm)
{
    uint32_t n = LOAD_RLX(&shm->channels);
    if (n < 1)
        return 1;
    return n > XRF_MAX_CHANNELS ? XRF_MAX_CHANNELS : n;
}

/* A char array the loop filled holds a C string: a NUL within it. */
static int terminated(const char *s, size_t n)
{
    return memchr(s, '\0', n) != NULL;
}

int xrf_log_meta_check(const struct xrf_log_meta *m, const struct xrf_ring *r, uint32_t capacity,
                       struct xrf_log_meta *out, struct xrf_ring_geom *g, uint64_t *tail)
{
    if (m == NULL || r == NULL || out == NULL || g == NULL || tail == NULL)
        return -EINVAL;
    if (LOAD_ACQ(&m->ready) == 0)
        return -EAGAIN;
    /* One copy, checked and used from here on: the loop may change the segment's meta at any
     * moment, the copy it cannot. The generation around it tells a copy torn by a (real)
     * re-publication, to be retried, from one the loop scribbled on, which the checks refuse. */
    uint64_t gen = LOAD_ACQ(&m->generation);
    memcpy(out, m, sizeof *out);
    uint64_t t = LOAD_ACQ(&r->tail);
    __atomic_thread_fence(__ATOMIC_ACQUIRE);
    if (LOAD_RLX(&m->generation) != gen)
        return -EAGAIN;
    out->ready = 1;
    out->generation = gen;

    if (out->writer != XRF_LOG_WRITER_PROCESS && out->writer != XRF_LOG_WRITER_HOST)
        return -EPROTO;
    if (out->nvars > XRF_LOG_VARS_MAX || !terminated(out->path, sizeof out->path))
        return -EPROTO;
    if (out->record_size > capacity || capacity - out->record_size < sizeof(struct xrf_slot_hdr))
        return -EPROTO;
    for (uint32_t i = 0; i < out->nvars; i++) {
        const struct xrf_log_var *v = &out->vars[i];
        const struct xrf_logfile_type *t = xrf_logfile_type_of(v->type);
        if (t == NULL || !terminated(v->name, sizeof v->name) || v->offset < 0 ||
            (uint64_t)(uint32_t)v->offset + t->size > out->record_size)
            return -EPROTO;
    }
    uint32_t slot_size = 0;
    uint32_t slots = xrf_log_slots_for(out->record_size, capacity, &slot_size);
    if (slots == 0)
        return -EPROTO;
    int rc = xrf_ring_geom_check(r, slots, slot_size, capacity, g);
    if (rc != 0)
        return -EPROTO; /* whichever way it differs, it is not what a logger sets */
    *tail = t;
    return 0;
}

/* The ring header no longer says the geometry the reader took: a loop never changes it after
 * setting it up, so one that does is writing where it should not. Compared, never used. */
static inline int ring_moved(const struct xrf_ring *r, const struct xrf_ring_geom *g)
{
    return LOAD_RLX(&r->slots) != g->slots || LOAD_RLX(&r->slot_size) != g->slot_size;
}

int xrf_bcast_read_g(const struct xrf_ring *r, const struct xrf_ring_geom *g, const void *slots,
                     uint64_t *cursor, void *out, uint64_t *lost)
{
    const uint64_t nslots = g->slots;
    if (ring_moved(r, g))
        return -EPROTO;
    for (int tries = 0; tries < XRF_SPIN_LIMIT; tries++) {
        uint64_t head = LOAD_ACQ(&r->head);
        uint64_t c = *cursor;
        if (c == head)
            return 0;
        if (c > head)
            return -EPROTO; /* publications are never taken back */
        if (head - c > nslots) {
            *lost += head - nslots - c;
            c = head - nslots;
            *cursor = c;
        }
        /* The index comes from the reader's cursor and geometry only. */
        const struct xrf_slot_hdr *slot =
            (const struct xrf_slot_hdr *)((const uint8_t *)slots +
                                          (size_t)(c & (nslots - 1)) * g->slot_size);
        uint64_t s1 = LOAD_ACQ(&slot->seq);
        if (s1 == 2 * c + 2) {
            xrf_seq_copy(out, slot, g->slot_size);
            __atomic_thread_fence(__ATOMIC_ACQUIRE);
            if (LOAD_RLX(&slot->seq) == s1) {
                *cursor = c + 1;
                return 1;
            }
        }
        /* The producer lapped this reader while it copied; the head check above catches up. */
        if (tries > 1000) {
            *lost += 1;
            *cursor = c + 1;
        }
    }
    return 0;
}

int xrf_spsc_peek_run_g(const struct xrf_ring *r, const struct xrf_ring_geom *g, const void *slots,
                        uint64_t tail, const void **first)
{
    *first = NULL;
    if (ring_moved(r, g))
        return -EPROTO;
    uint64_t head = LOAD_ACQ(&r->head);
    uint64_t ready = head - tail; /* a head behind the tail wraps to a huge count */
    if (ready == 0)
        return 0;
    if (ready > g->slots)
        return -EPROTO;
    uint64_t at = tail & (g->slots - 1);
    uint64_t to_end = g->slots - at;
    *first = (const uint8_t *)slots + (size_t)at * g->slot_size;
    return (int)(ready < to_end ? ready : to_end);
}

void xrf_spsc_release_g(struct xrf_ring *r, uint64_t *tail, uint32_t n)
{
    *tail += n;
    STORE_REL(&r->tail, *tail);
}

/* ---- doorbell ------------------------------------------------------------------------------ */

/* The doorbell is a store-then-load on each side (Dekker): the loop bumps `doorbell` then reads
 * `doorbell_waiters`; a host bumps `doorbell_waiters` then reads `doorbell` before it sleeps.
 * With RELEASE/ACQUIRE (what this was) each side's load may be satisfied before its own store
 * is visible to the other -- allowed by C11 and done by an Arm core's store buffer (and its
 * RCpc LDAPR) -- so both could miss each other: the loop sees no waiter and does not wake, the
 * host sees the old doorbell and sleeps through a publication until its timeout. SEQ_CST on all
 * four accesses forbids that outcome (one total order: at least one side sees the other's
 * store). The bump also RELEASEs what the loop published before it. On arm64 this is LDADDAL and
 * LDAR, once a doorbell period. */
int xrf_doorbell_should_ring(struct xrf_shm *shm)
{
    __atomic_add_fetch(&shm->doorbell, 1u, __ATOMIC_SEQ_CST);
    return __atomic_load_n(&shm->doorbell_waiters, __ATOMIC_SEQ_CST) != 0;
}

int xrf_doorbell_wake(struct xrf_shm *shm)
{
    long r = syscall(SYS_futex, &shm->doorbell, FUTEX_WAKE, INT_MAX, NULL, NULL, 0);
    return r < 0 ? -errno : (int)r;
}

uint32_t xrf_doorbell_wait(struct xrf_shm *shm, uint32_t seen, int timeout_ms)
{
    /* SEQ_CST: the host's half of the Dekker pair above. If the loop's bump comes after this
     * load, the loop sees this waiter and wakes it; FUTEX_WAIT itself compares the word again. */
    __atomic_add_fetch(&shm->doorbell_waiters, 1u, __ATOMIC_SEQ_CST);
    if (__atomic_load_n(&shm->doorbell, __ATOMIC_SEQ_CST) == seen) {
        struct timespec ts = {timeout_ms / 1000, (long)(timeout_ms % 1000) * 1000000L};
        syscall(SYS_futex, &shm->doorbell, FUTEX_WAIT, seen, timeout_ms >= 0 ? &ts : NULL, NULL, 0);
    }
    __atomic_sub_fetch(&shm->doorbell_waiters, 1u, __ATOMIC_ACQ_REL);
    return LOAD_ACQ(&shm->doorbell);
}

/* ---- the command table --------------------------------------------------------------------- */

int32_t xrf_cmd_transition(int32_t state, int32_t cmd)
{
    switch (cmd) {
    case XRF_CMD_INITIALISE:
        if (state == XRF_STATE_IDLE)
            return XRF_STATE_INITIALISING;
        break;
    case XRF_CMD_START:
        if (state == XRF_STATE_INITIALISED || state == XRF_STATE_PAUSED)
            return XRF_STATE_RUN;
        break;
    case XRF_CMD_STOP:
        if (state == XRF_STATE_RUN || state == XRF_STATE_PAUSED)
            return XRF_STATE_STOPPING;
        break;
    case XRF_CMD_RESET:
        /* PAUSED is allowed too (the thesis lists it): reset is allowed from RUN, and a paused
         * controller is no further from a safe re-initialisation than a running one. */
        if (state == XRF_STATE_RUN || state == XRF_STATE_STOPPED || state == XRF_STATE_ERROR ||
            state == XRF_STATE_PAUSED)
            return XRF_STATE_INITIALISING;
        break;
    case XRF_CMD_PAUSE:
        if (state == XRF_STATE_RUN)
            return XRF_STATE_PAUSING;
        break;
    case XRF_CMD_QUIT:
        if (state == XRF_STATE_STOPPED || state == XRF_STATE_ERROR)
            return XRF_STATE_QUIT;
        break;
    default:
        return -XRF_REJECT_UNKNOWN;
    }
    return -XRF_REJECT_NOT_ALLOWED;
}

int32_t xrf_state_complete(int32_t state)
{
    switch (state) {
    case XRF_STATE_INITIALISING:
        return XRF_STATE_INITIALISED;
    case XRF_STATE_INITIALISED:
        return XRF_STATE_RUN;
    case XRF_STATE_RUN:
        return XRF_STATE_STOPPING;
    case XRF_STATE_STOPPING:
        return XRF_STATE_STOPPED;
    case XRF_STATE_PAUSING:
        return XRF_STATE_PAUSED;
    default:
        return 0; /* STOPPED, PAUSED, ERROR: "complete" leads nowhere; IDLE, QUIT: no hook */
    }
}

/* The numbers of XRF_STATES and XRF_CMDS are 1..count: the switches below make a number given
 * twice a compile error (duplicate case), these a number outside the range. Hosts (names.py)
 * walk 1..count. */
#define XRF_STATE_IN_RANGE_(NAME, number) \
    _Static_assert((number) >= 1 && (number) <= XRF_STATE_COUNT, #NAME ": not in 1..count");
#define XRF_CMD_IN_RANGE_(NAME, name, number, safe) \
    _Static_assert((number) >= 1 && (number) <= XRF_CMD_COUNT, #NAME ": not in 1..count");
XRF_STATES(XRF_STATE_IN_RANGE_)
XRF_CMDS(XRF_CMD_IN_RANGE_)

void xrf_cmd_reject_reason(int32_t state, int32_t cmd, char *buf, size_t len)
{
    if (len == 0)
        return;
    if (xrf_cmd_transition(state, cmd) == -XRF_REJECT_UNKNOWN) {
        /* "5 is not a command (1 initialise, 2 start, ...)", the list from XRF_CMDS */
        int n = snprintf(buf, len, "%d is not a command (", cmd);
        for (int32_t c = 1; c <= XRF_CMD_COUNT && n > 0 && (size_t)n < len; c++)
            n += snprintf(buf + n, len - (size_t)n, "%s%d %s", c > 1 ? ", " : "", c,
                          xrf_cmd_name(c));
        if (n > 0 && (size_t)n < len)
            snprintf(buf + n, len - (size_t)n, ")");
        return;
    }
    int n = snprintf(buf, len, "%s is not allowed in state %s; allowed:", xrf_cmd_name(cmd),
                     xrf_state_name(state));
    int any = 0;
    for (int32_t c = 1; c <= XRF_CMD_COUNT && n > 0 && (size_t)n < len; c++) {
        if (xrf_cmd_transition(state, c) > 0) {
            n += snprintf(buf + n, len - (size_t)n, " %s", xrf_cmd_name(c));
            any = 1;
        }
    }
    if (!any && n > 0 && (size_t)n < len)
        snprintf(buf + n, len - (size_t)n, " none");
}

#define XRF_STATE_NAME_CASE_(NAME, number) \
    case number:                           \
        return #NAME;
const char *xrf_state_name(int32_t state)
{
    switch (state) {
        XRF_STATES(XRF_STATE_NAME_CASE_)
    default:
        return "?";
    }
}

#define XRF_CMD_NAME_CASE_(NAME, name, number, safe) \
    case number:                                     \
        return #name;
const char *xrf_cmd_name(int32_t cmd)
{
    switch (cmd) {
        XRF_CMDS(XRF_CMD_NAME_CASE_)
    default:
        return "?";
    }
}

#define XRF_CMD_SAFE_CASE_(NAME, name, number, safe) \
    case number:                                     \
        return safe;
int xrf_cmd_safe(int32_t cmd)
{
    switch (cmd) {
        XRF_CMDS(XRF_CMD_SAFE_CASE_)
    default:
        return 0;
    }
}

#define XRF_TRANSPORT_NAME_(NAME, name) name,
const char *xrf_transport_name(int32_t transport)
{
    static const char *const names[] = {XRF_TRANSPORTS(XRF_TRANSPORT_NAME_)};
    return (transport >= 0 && transport < XRF_TRANSPORT_COUNT) ? names[transport] : NULL;
}

#define XRF_HOST_LOST_ACTION_CASE_(NAME, name, number) \
    case number:                                       \
        return name;
const char *xrf_host_lost_action_name(int32_t action)
{
    switch (action) {
        XRF_HOST_LOST_ACTIONS(XRF_HOST_LOST_ACTION_CASE_)
    default:
        return NULL;
    }
}

#define XRF_HOST_LOST_ACTION_MATCH_(NAME, name, number) \
    if (strcmp(text, name) == 0)                        \
        return number;
int32_t xrf_host_lost_action_parse(const char *text)
{
    XRF_HOST_LOST_ACTIONS(XRF_HOST_LOST_ACTION_MATCH_)
    return -EINVAL;
}
