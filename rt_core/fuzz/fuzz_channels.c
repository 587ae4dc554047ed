/*
 * libFuzzer harness of the host side of xrf/channels.h (issue 26): everything the appliance reads
 * from a loop's shared segment is written by a guest, so every host-side reader and writer of
 * channels.c and logformat.c is driven over arbitrary segment bytes that also change while the
 * host reads them, the way the appliance calls them: attach (xrf_shm_check, the geometry taken
 * once), status (xrf_status_read), commands (xrf_cmd_send), ros2xeno (xrf_data_in_write), the
 * telemetry and monitor rings (xrf_bcast_read_g, a live reader and one from the start), the log
 * and timing channels (xrf_log_meta_check whenever the generation moves, xrf_logfile_header of the
 * checked copy, xrf_spsc_peek_run_g and xrf_spsc_release_g as the host writer does) and the
 * doorbell (xrf_doorbell_wait, timeout 0).
 *
 * The segment: a private mapping of a template segment (initialised as an honest loop leaves it,
 * its logger published) of exactly sizeof(struct xrf_shm), with inaccessible guard space on both
 * sides, so a read or write one byte outside it faults as it would in the appliance (ASan adds
 * overflows of the host's own buffers, UBSan undefined arithmetic and misaligned access). Each
 * input starts from the template again (madvise(MADV_DONTNEED) drops the private copies of the
 * pages it changed).
 *
 * The input is a script of operations (struct op below); each opcode byte says when its
 * operation runs:
 *   - setup:       before the host attaches;
 *   - interleaved: one at a time between two host calls (deterministic, reproducible);
 *   - concurrent:  in a second thread that repeats them while the host reads (a guest racing
 *                  the host: torn seqlocks, heads moving under a copy).
 * Operations are a guest's: store any value into a field of the layout (head, tail, slots,
 * slot_size, seq, size, nvars...), store raw bytes anywhere in the segment, or behave like an
 * honest loop (publish telemetry, push log records, republish the logger's layout...). The honest
 * ones index the rings with the geometry the loop set up (never with what is in the segment), so
 * the guest side of this harness never leaves the segment itself: any fault is the host's.
 *
 * On top of the sanitizers the harness checks the contracts the appliance's code relies on (see
 * contract()): a run of log records lies inside its ring, a layout xrf_log_meta_check accepted is
 * one the writer can use, and every call returns (libFuzzer's -timeout catches a host spinning
 * for ever on guest data).
 *
 * XRF_FUZZ_WRITE_SEEDS=<folder> makes the harness write its seed corpus (the seeds[] below) into
 * <folder> and exit: rt_core/fuzz/corpus/channels/ is that output, so the opcodes are defined in
 * this file only. Build: cmake -DXRF_FUZZ=ON with clang (rt_core/CMakeLists.txt); run:
 * tests/rt_core/test_fuzz_channels.py (a short budget) and bench/rt_core/fuzz_channels.py.
 */
#define _GNU_SOURCE
#include "xrf/channels.h"
#include "xrf/logformat.h"

#include <pthread.h>
#include <sanitizer/asan_interface.h>
#include <sched.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <unistd.h>

/* ---- the segment ------------------------------------------------------------------------- */

/* Inaccessible address space on each side of the segment: a host that indexes a ring with a
 * guest's geometry lands here (or further, where nothing is mapped) and faults. */
#define GUARD_BYTES ((size_t)16 << 30)

static struct xrf_shm *shm; /* the segment under test (a private view of the template) */
static uint8_t *map_base;   /* its pages */
static size_t map_len;      /* sizeof(struct xrf_shm) rounded up to pages */
/* The log ring's geometry as the honest logger last published it: slots << 32 | slot_size, one
 * word, so that a thread never pairs one layout's slot count with another's slot size. */
static uint64_t log_geometry;

/* Fields a guest's store may target (any byte of the segment is reachable through OP_RAW too;
 * naming these makes the fuzzer find the interesting ones at once). */
struct field {
    const char *name;
    size_t offset;
    size_t width;
};
#define FIELD(name, offset, width) \
    {                              \
        name, offset, width        \
    }
#define F(m) FIELD(#m, offsetof(struct xrf_shm, m), sizeof(((struct xrf_shm *)0)->m))
#define RING_FIELDS(r) F(r.head), F(r.tail), F(r.slots), F(r.slot_size), F(r.dropped)
#define META_FIELDS(m)                                                                      \
    F(m.ready), F(m.nvars), F(m.record_size), F(m.writer), F(m.generation), F(m.file_mode), \
        F(m.vars[0].type), F(m.vars[0].offset), F(m.vars[1].offset), F(m.vars[99].offset)
static const struct field fields[] = {
    F(magic),
    F(version),
    F(size),
    F(ready),
    F(channels),
    F(info.pid),
    F(info.cycle_freq),
    F(info.ros2xeno_size),
    F(info.xeno2ros_size),
    F(info.doorbell_period_cycles),
    F(host_heartbeat_ns),
    F(host_timeout_ms),
    F(doorbell),
    F(doorbell_waiters),
    F(status.seq),
    F(status.state),
    F(status.cycles),
    F(cmd.head),
    F(cmd.tail),
    F(cmd.slot[0].seq),
    F(cmd.slot[1].seq),
    F(cmd.slot[63].seq),
    F(ros2xeno.seq),
    F(ros2xeno.size),
    F(sim.forced_off),
    RING_FIELDS(telem_ring),
    F(telem[0].hdr.seq),
    F(telem[0].size),
    RING_FIELDS(monitor_ring),
    F(monitor[0].hdr.seq),
    F(monitor[0].len),
    META_FIELDS(log_meta),
    RING_FIELDS(log_ring),
    META_FIELDS(timing_meta),
    RING_FIELDS(timing_ring),
};
#define NFIELDS (sizeof fields / sizeof fields[0])

static void store_field(const struct field *f, uint64_t v)
{
    void *p = (uint8_t *)shm + f->offset;
    switch (f->width) {
    case 1:
        __atomic_store_n((uint8_t *)p, (uint8_t)v, __ATOMIC_RELEASE);
        break;
    case 2:
        __atomic_store_n((uint16_t *)p, (uint16_t)v, __ATOMIC_RELEASE);
        break;
    case 4:
        __atomic_store_n((uint32_t *)p, (uint32_t)v, __ATOMIC_RELEASE);
        break;
    default:
        __atomic_store_n((uint64_t *)p, v, __ATOMIC_RELEASE);
        break;
    }
}

static uint64_t load_field(const struct field *f)
{
    const void *p = (const uint8_t *)shm + f->offset;
    switch (f->width) {
    case 1:
        return __atomic_load_n((const uint8_t *)p, __ATOMIC_ACQUIRE);
    case 2:
        return __atomic_load_n((const uint16_t *)p, __ATOMIC_ACQUIRE);
    case 4:
        return __atomic_load_n((const uint32_t *)p, __ATOMIC_ACQUIRE);
    default:
        return __atomic_load_n((const uint64_t *)p, __ATOMIC_ACQUIRE);
    }
}

/* The honest logger's publication (xrf2_logger.cpp's publish()): layout, then ring, then
 * generation and ready. nvars variables of type double, packed. */
static void publish_log_layout(struct xrf_shm *s, uint32_t record_size, uint32_t nvars)
{
    struct xrf_log_meta *m = &s->log_meta;
    if (nvars > XRF_LOG_VARS_MAX)
        nvars = XRF_LOG_VARS_MAX;
    uint32_t slot_size = 0;
    uint32_t slots = xrf_log_slots_for(record_size, XRF_LOG_RING_BYTES, &slot_size);
    m->nvars = nvars;
    m->record_size = record_size;
    m->file_mode = 0640;
    m->writer = XRF_LOG_WRITER_HOST;
    snprintf(m->path, sizeof m->path, "log-%u.xrflog", record_size);
    for (uint32_t i = 0; i < nvars; i++) {
        snprintf(m->vars[i].name, sizeof m->vars[i].name, "v%u", i);
        m->vars[i].type = XRF_LOG_DOUBLE;
        m->vars[i].offset = (int32_t)(8 * i);
    }
    xrf_ring_init(&s->log_ring, slots, slot_size);
    __atomic_store_n(&log_geometry, (uint64_t)slots << 32 | slot_size, __ATOMIC_RELAXED);
    __atomic_store_n(&m->generation, m->generation + 1, __ATOMIC_RELEASE);
    __atomic_store_n(&m->ready, 1u, __ATOMIC_RELEASE);
}

#define TEMPLATE_RECORD 16 /* the template logger: two doubles */

/* The template: a segment as an honest loop leaves it after start-up, logger and timing on. */
static void init_template(struct xrf_shm *s)
{
    xrf_shm_init(s);
    s->info.pid = 4242;
    s->info.cycle_freq = 1000;
    s->info.write_decimator_freq = 1000;
    s->info.monitor_freq = 10;
    s->info.ros2xeno_size = 16;
    s->info.xeno2ros_size = 16;
    s->info.doorbell_period_cycles = 1;
    snprintf(s->info.program, sizeof s->info.program, "fuzz");
    s->status.state = XRF_STATE_RUN;
    s->status.running = 1;
    publish_log_layout(s, TEMPLATE_RECORD, TEMPLATE_RECORD / 8);
    xrf_ring_init(&s->timing_ring, XRF_TIMING_SLOTS, sizeof(struct xrf_timing_record));
    xrf_timing_meta_init(&s->timing_meta, XRF_LOG_WRITER_HOST, "timing.xrflog");
    xrf_shm_publish_ready(s);
}

static void map_segment(void)
{
    long page = sysconf(_SC_PAGESIZE);
    map_len = (sizeof(struct xrf_shm) + (size_t)page - 1) & ~((size_t)page - 1);
    int fd = memfd_create("xrf-fuzz-segment", MFD_CLOEXEC);
    if (fd < 0 || ftruncate(fd, (off_t)map_len) != 0) {
        perror("fuzz_channels: memfd");
        abort();
    }
    /* The segment ends where the guard begins: one byte past it faults. */
    size_t lead = map_len - sizeof(struct xrf_shm);
    uint8_t *tmpl = mmap(NULL, map_len, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
    uint8_t *space = mmap(NULL, GUARD_BYTES + map_len + GUARD_BYTES, PROT_NONE,
                          MAP_PRIVATE | MAP_ANONYMOUS | MAP_NORESERVE, -1, 0);
    if (tmpl == MAP_FAILED || space == MAP_FAILED) {
        perror("fuzz_channels: mmap");
        abort();
    }
    init_template((struct xrf_shm *)(tmpl + lead));
    munmap(tmpl, map_len);
    map_base =
        mmap(space + GUARD_BYTES, map_len, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_FIXED, fd, 0);
    if (map_base == MAP_FAILED) {
        perror("fuzz_channels: mmap");
        abort();
    }
    close(fd);
    ASAN_POISON_MEMORY_REGION(map_base, lead); /* the page's bytes before the segment */
    shm = (struct xrf_shm *)(map_base + lead);
}

static void reset_segment(void)
{
    /* Private pages go back to the template's; untouched ones cost nothing. */
    if (madvise(map_base, map_len, MADV_DONTNEED) != 0) {
        perror("fuzz_channels: madvise");
        abort();
    }
    uint32_t slot_size = 0;
    uint32_t slots = xrf_log_slots_for(TEMPLATE_RECORD, XRF_LOG_RING_BYTES, &slot_size);
    log_geometry = (uint64_t)slots << 32 | slot_size;
}

/* ---- the script ---------------------------------------------------------------------------- */

enum op_kind {
    OP_STORE,        /* u8 field, u64 value: a guest stores any value into a field */
    OP_ADD,          /* u8 field, i32 delta: ... or moves it (a head running ahead, back) */
    OP_RAW,          /* u32 offset, u8 n (n % 65), n bytes: raw bytes anywhere */
    OP_SLOT_SEQ,     /* u8 ring, u16 slot, u64 value: a slot's sequence word */
    OP_PUB_TELEM,    /* u8 n: the loop publishes n telemetry samples */
    OP_PUB_MONITOR,  /* u8 n: n monitor lines */
    OP_LOG_PUSH,     /* u8 n: n records into the log ring (dropped when full) */
    OP_TIMING_PUSH,  /* u8 n: n timing records */
    OP_STATUS_BEGIN, /* the status seqlock made odd (a write in progress) */
    OP_STATUS_END,   /* ... and even again */
    OP_CMD_POLL,     /* u8 n: the loop takes up to n commands */
    OP_DOORBELL,     /* the loop rings the doorbell */
    OP_LOG_PUBLISH,  /* u16 record_size, u8 nvars: the logger publishes a new layout */
    OP_SPIN,         /* u16 n: busy for n iterations (shifts the race) */
    OP_FILL,         /* u32 offset, u16 n, u8 byte: n bytes set anywhere */
    OP_YIELD,        /* sched_yield() */
    OP_KINDS
};

/* The opcode byte: kind in the low 4 bits, phase in the top 2 (bits 4-5 are ignored). */
#define PHASE_SETUP 0
#define PHASE_INTERLEAVED 1
#define PHASE_CONCURRENT 2
#define PHASE_SETUP_TOO 3
#define OPCODE(phase, kind) ((uint8_t)((phase) << 6 | (kind)))

/* Rings an OP_SLOT_SEQ may address. */
enum { RING_TELEM, RING_MONITOR, RING_LOG, RING_TIMING, RING_CMD, RING_KINDS };

struct op {
    uint8_t kind;
    uint8_t a8;
    uint16_t a16;
    uint32_t a32;
    uint64_t a64;
    const uint8_t *bytes; /* OP_RAW's bytes (in the input, which outlives the run) */
};

#define MAX_OPS 256

struct script {
    struct op setup[MAX_OPS], interleaved[MAX_OPS], concurrent[MAX_OPS];
    size_t nsetup, ninterleaved, nconcurrent;
};

struct reader {
    const uint8_t *p, *end;
};

/* Little-endian integers; an input that ends early reads zeros. */
static uint64_t take(struct reader *r, int bytes)
{
    uint64_t v = 0;
    for (int i = 0; i < bytes; i++)
        v |= (uint64_t)(r->p < r->end ? *r->p++ : 0) << (8 * i);
    return v;
}

static void parse(const uint8_t *data, size_t size, struct script *s)
{
    struct reader r = {data, data + size};
    s->nsetup = s->ninterleaved = s->nconcurrent = 0;
    while (r.p < r.end) {
        uint8_t code = *r.p++;
        struct op o = {.kind = code & 15};
        switch (o.kind) {
        case OP_STORE:
            o.a8 = (uint8_t)take(&r, 1);
            o.a64 = take(&r, 8);
            break;
        case OP_ADD:
            o.a8 = (uint8_t)take(&r, 1);
            o.a32 = (uint32_t)take(&r, 4);
            break;
        case OP_RAW:
            o.a32 = (uint32_t)take(&r, 4);
            o.a8 = (uint8_t)(take(&r, 1) % 65);
            if ((size_t)(r.end - r.p) < o.a8)
                o.a8 = (uint8_t)(r.end - r.p);
            o.bytes = r.p;
            r.p += o.a8;
            break;
        case OP_SLOT_SEQ:
            o.a8 = (uint8_t)take(&r, 1);
            o.a16 = (uint16_t)take(&r, 2);
            o.a64 = take(&r, 8);
            break;
        case OP_PUB_TELEM:
        case OP_PUB_MONITOR:
        case OP_LOG_PUSH:
        case OP_TIMING_PUSH:
        case OP_CMD_POLL:
            o.a8 = (uint8_t)take(&r, 1);
            break;
        case OP_LOG_PUBLISH:
            o.a16 = (uint16_t)take(&r, 2);
            o.a8 = (uint8_t)take(&r, 1);
            break;
        case OP_SPIN:
            o.a16 = (uint16_t)take(&r, 2);
            break;
        case OP_FILL:
            o.a32 = (uint32_t)take(&r, 4);
            o.a16 = (uint16_t)take(&r, 2);
            o.a8 = (uint8_t)take(&r, 1);
            break;
        default: /* no arguments */
            break;
        }
        switch (code >> 6) {
        case PHASE_INTERLEAVED:
            if (s->ninterleaved < MAX_OPS)
                s->interleaved[s->ninterleaved++] = o;
            break;
        case PHASE_CONCURRENT:
            if (s->nconcurrent < MAX_OPS)
                s->concurrent[s->nconcurrent++] = o;
            break;
        default:
            if (s->nsetup < MAX_OPS)
                s->setup[s->nsetup++] = o;
            break;
        }
    }
}

/* ---- the guest's operations ---------------------------------------------------------------- */

/* The loop's side of a broadcast ring, with the ring's real geometry: slot = head % slots. */
static void honest_bcast(struct xrf_ring *r, struct xrf_slot_hdr *slot0, uint32_t slots,
                         size_t slot_size, unsigned n)
{
    for (unsigned i = 0; i < n; i++) {
        uint64_t head = __atomic_load_n(&r->head, __ATOMIC_RELAXED);
        struct xrf_slot_hdr *slot =
            (struct xrf_slot_hdr *)((uint8_t *)slot0 + (size_t)(head % slots) * slot_size);
        __atomic_store_n(&slot->seq, 2 * head + 1, __ATOMIC_RELAXED);
        __atomic_thread_fence(__ATOMIC_RELEASE);
        slot->cycle = head;
        slot->t_ns = (int64_t)(head * 1000000u); /* any value: a guest's head */
        __atomic_store_n(&slot->seq, 2 * head + 2, __ATOMIC_RELEASE);
        __atomic_store_n(&r->head, head + 1, __ATOMIC_RELEASE);
    }
}

/* The loop's side of an SPSC ring: full when head - tail >= slots, as the loop sees it. */
static void honest_spsc(struct xrf_ring *r, uint8_t *slot0, uint32_t slots, size_t slot_size,
                        unsigned n)
{
    if (slots == 0)
        return;
    for (unsigned i = 0; i < n; i++) {
        uint64_t head = __atomic_load_n(&r->head, __ATOMIC_RELAXED);
        if (head - __atomic_load_n(&r->tail, __ATOMIC_ACQUIRE) >= slots) {
            __atomic_store_n(&r->dropped, r->dropped + 1, __ATOMIC_RELAXED);
            continue;
        }
        struct xrf_slot_hdr *slot =
            (struct xrf_slot_hdr *)(slot0 + (size_t)(head % slots) * slot_size);
        slot->seq = head;
        slot->cycle = head;
        slot->t_ns = (int64_t)(head & INT64_MAX);
        __atomic_store_n(&r->head, head + 1, __ATOMIC_RELEASE);
    }
}

static void honest_cmd_poll(unsigned n)
{
    for (unsigned i = 0; i < n; i++) {
        uint64_t pos = __atomic_load_n(&shm->cmd.tail, __ATOMIC_RELAXED);
        struct xrf_cmd_slot *slot = &shm->cmd.slot[pos % XRF_CMD_SLOTS];
        if (__atomic_load_n(&slot->seq, __ATOMIC_ACQUIRE) != pos + 1)
            return;
        __atomic_store_n(&slot->seq, pos + XRF_CMD_SLOTS, __ATOMIC_RELEASE);
        __atomic_store_n(&shm->cmd.tail, pos + 1, __ATOMIC_RELEASE);
    }
}

static uint64_t *slot_seq(uint8_t ring, uint16_t index)
{
    switch (ring % RING_KINDS) {
    case RING_TELEM:
        return &shm->telem[index % XRF_TELEM_SLOTS].hdr.seq;
    case RING_MONITOR:
        return &shm->monitor[index % XRF_MONITOR_SLOTS].hdr.seq;
    case RING_LOG: {
        uint64_t g = __atomic_load_n(&log_geometry, __ATOMIC_RELAXED);
        uint32_t slots = (uint32_t)(g >> 32) ? (uint32_t)(g >> 32) : 1;
        return (uint64_t *)(shm->log_data + (size_t)(index % slots) * (uint32_t)g);
    }
    case RING_TIMING:
        return &shm->timing[index % XRF_TIMING_SLOTS].hdr.seq;
    default:
        return &shm->cmd.slot[index % XRF_CMD_SLOTS].seq;
    }
}

static void apply(const struct op *o)
{
    switch (o->kind) {
    case OP_STORE:
        store_field(&fields[o->a8 % NFIELDS], o->a64);
        break;
    case OP_ADD: {
        const struct field *f = &fields[o->a8 % NFIELDS];
        store_field(f, load_field(f) + (uint64_t)(int64_t)(int32_t)o->a32);
        break;
    }
    case OP_RAW:
        if (o->a8)
            memcpy((uint8_t *)shm + o->a32 % (sizeof(struct xrf_shm) - o->a8 + 1), o->bytes, o->a8);
        break;
    case OP_SLOT_SEQ:
        __atomic_store_n(slot_seq(o->a8, o->a16), o->a64, __ATOMIC_RELEASE);
        break;
    case OP_PUB_TELEM:
        honest_bcast(&shm->telem_ring, &shm->telem[0].hdr, XRF_TELEM_SLOTS,
                     sizeof(struct xrf_telemetry), o->a8);
        break;
    case OP_PUB_MONITOR:
        honest_bcast(&shm->monitor_ring, &shm->monitor[0].hdr, XRF_MONITOR_SLOTS,
                     sizeof(struct xrf_monitor_line), o->a8);
        break;
    case OP_LOG_PUSH: {
        uint64_t g = __atomic_load_n(&log_geometry, __ATOMIC_RELAXED);
        honest_spsc(&shm->log_ring, shm->log_data, (uint32_t)(g >> 32), (uint32_t)g, o->a8);
        break;
    }
    case OP_TIMING_PUSH:
        honest_spsc(&shm->timing_ring, (uint8_t *)shm->timing, XRF_TIMING_SLOTS,
                    sizeof(struct xrf_timing_record), o->a8);
        break;
    case OP_STATUS_BEGIN:
    case OP_STATUS_END:
        __atomic_add_fetch(&shm->status.seq, 1u, __ATOMIC_RELEASE);
        break;
    case OP_CMD_POLL:
        honest_cmd_poll(o->a8);
        break;
    case OP_DOORBELL:
        __atomic_add_fetch(&shm->doorbell, 1u, __ATOMIC_RELEASE);
        break;
    case OP_LOG_PUBLISH:
        /* Any record size an honest logger could have (up to what fits the ring twice). */
        publish_log_layout(shm, 8u * (1u + o->a16 % 4096u), o->a8);
        break;
    case OP_SPIN:
        for (volatile unsigned i = 0; i < o->a16; i++) {}
        break;
    case OP_FILL: {
        size_t n = o->a16 % sizeof(struct xrf_shm);
        memset((uint8_t *)shm + o->a32 % (sizeof(struct xrf_shm) - n + 1), o->a8, n);
        break;
    }
    default:
        sched_yield();
        break;
    }
}

/* The racing guest: repeats its operations until the host is done. Interleaved operations run
 * meanwhile on the host's thread: two loop writers at once, which a guest with threads may be;
 * only the segment's contents suffer, each stays inside the segment. */
struct racer {
    const struct script *s;
    int done;
};

static void *race(void *arg)
{
    struct racer *r = arg;
    while (!__atomic_load_n(&r->done, __ATOMIC_ACQUIRE))
        for (size_t i = 0; i < r->s->nconcurrent; i++)
            apply(&r->s->concurrent[i]);
    return NULL;
}

/* ---- the host: every call the appliance makes ---------------------------------------------- */

#define ROUNDS 3
#define READ_LIMIT 64 /* publications read per broadcast reader per round */

static volatile uint64_t sink; /* keeps the reads of the log records */

static void contract(int ok, const char *what)
{
    if (!ok) {
        fprintf(stderr, "fuzz_channels: contract broken: %s\n", what);
        abort();
    }
}

/* A log channel as the host writer holds it (xrflab/logs/log_channel.py): the layout copied and
 * checked, its ring's geometry and the read position, all in the host's memory. */
struct log_host {
    struct xrf_log_meta *meta;
    struct xrf_ring_geom geom;
    uint64_t tail;
    int taken;
};

struct host {
    struct xrf_shm_geom geom; /* taken at attach (xrf_shm_check) */
    uint64_t telem_live, telem_start, monitor_live, monitor_start, lost;
    uint32_t doorbell;
    struct log_host log, timing;
    struct xrf_status *status;       /* each out-buffer exactly the size of its type: */
    struct xrf_telemetry *telemetry; /* ASan sees a copy larger than it */
    struct xrf_monitor_line *monitor;
    char *header;
};

static void host_bcast(const struct xrf_ring *r, const struct xrf_ring_geom *g, const void *slots,
                       uint64_t *cursor, void *out, struct host *h)
{
    /* After -EPROTO the appliance stops the run; the reader is called on regardless: a refusal
     * must be as safe as a read. */
    for (int i = 0; i < READ_LIMIT; i++)
        if (xrf_bcast_read_g(r, g, slots, cursor, out, &h->lost) != 1)
            break;
}

/* What xrf_log_meta_check promises of the copy it accepted: the writer and the header composer
 * rely on it. */
static void check_layout(const struct xrf_log_meta *m, const struct xrf_ring_geom *g,
                         size_t capacity)
{
    contract(m->nvars <= XRF_LOG_VARS_MAX, "xrf_log_meta_check: nvars over the maximum");
    contract(memchr(m->path, 0, sizeof m->path) != NULL, "xrf_log_meta_check: path unterminated");
    for (uint32_t i = 0; i < m->nvars; i++) {
        const struct xrf_logfile_type *t = xrf_logfile_type_of(m->vars[i].type);
        contract(t != NULL && m->vars[i].offset >= 0 &&
                     (uint64_t)m->vars[i].offset + t->size <= m->record_size,
                 "xrf_log_meta_check: a variable outside the record");
        contract(memchr(m->vars[i].name, 0, sizeof m->vars[i].name) != NULL,
                 "xrf_log_meta_check: a name unterminated");
    }
    contract(g->slots > 0 && (g->slots & (g->slots - 1)) == 0 && g->slot_size % 8 == 0 &&
                 g->slot_size >= sizeof(struct xrf_slot_hdr) + m->record_size &&
                 (uint64_t)g->slots * g->slot_size <= capacity,
             "xrf_log_meta_check: a geometry that does not fit its ring");
}

/* The host log writer (xrflab/logs/host_writer.py): take the layout when the loop published a
 * new one (and compose its file's segment header), then the run of ready records: each record's
 * seq read, the run's bytes written out (here: summed), then released. */
static void host_log(struct host *h, struct log_host *lh, const struct xrf_log_meta *m,
                     struct xrf_ring *r, const void *slots, size_t capacity)
{
    uint64_t generation = __atomic_load_n(&m->generation, __ATOMIC_ACQUIRE);
    if (!lh->taken || generation != lh->meta->generation) {
        struct xrf_log_meta *copy = malloc(sizeof *copy);
        struct xrf_ring_geom g;
        uint64_t tail = 0;
        if (copy == NULL)
            abort();
        if (xrf_log_meta_check(m, r, (uint32_t)capacity, copy, &g, &tail) == 0) {
            check_layout(copy, &g, capacity);
            free(lh->meta);
            lh->meta = copy;
            lh->geom = g;
            lh->tail = tail;
            lh->taken = 1;
            struct xrf_logfile_ident id = {.program = "fuzz",
                                           .project = "p",
                                           .build = "b",
                                           .run = "r",
                                           .pid = 1,
                                           .cycle_freq = 1000};
            int n = xrf_logfile_header(h->header, XRF_LOGFILE_HEADER_MAX, &id, lh->meta,
                                       lh->geom.slot_size);
            contract(n <= XRF_LOGFILE_HEADER_MAX, "xrf_logfile_header: longer than its bound");
        } else {
            free(copy); /* the previous layout (if any) is kept */
        }
    }
    if (!lh->taken)
        return;
    const uint8_t *base = slots;
    const void *first = NULL;
    int count = xrf_spsc_peek_run_g(r, &lh->geom, slots, lh->tail, &first);
    if (count <= 0)
        return;
    const uint8_t *p = first;
    size_t stride = lh->geom.slot_size;
    contract(count <= (int)lh->geom.slots, "xrf_spsc_peek_run_g: more records than slots");
    contract(p >= base && p < base + capacity, "xrf_spsc_peek_run_g: run starts outside its ring");
    contract((size_t)count * stride <= (size_t)(base + capacity - p),
             "xrf_spsc_peek_run_g: count * slot_size runs past its ring");
    /* The first and last record's seq (the writer's recovery reads the leading ones), then
     * every cache line of the run, as write() would. */
    uint64_t sum = 0, seq = 0;
    memcpy(&seq, p, sizeof seq);
    sum = seq;
    memcpy(&seq, p + (size_t)(count - 1) * stride, sizeof seq);
    sum += seq;
    for (size_t i = 0; i < (size_t)count * stride; i += 64)
        sum += p[i];
    sink = sum;
    xrf_spsc_release_g(r, &lh->tail, (uint32_t)count);
}

static void host_round(struct host *h, int round, const struct script *s, size_t *next)
{
    /* Between two calls the next interleaved operation (if any) runs. */
#define STEP(call)                             \
    do {                                       \
        call;                                  \
        if (*next < s->ninterleaved)           \
            apply(&s->interleaved[(*next)++]); \
    } while (0)
    static const uint8_t payload[XRF_MSG_MAX] = {1, 2, 3};
    STEP(xrf_status_read(&shm->status, h->status));
    STEP(xrf_cmd_send(&shm->cmd, 1 + round % 6, XRF_SOURCE_APPLIANCE, round));
    STEP(xrf_data_in_write(&shm->ros2xeno, payload, (uint32_t)(16 << round) % XRF_MSG_MAX, round));
    STEP(host_bcast(&shm->telem_ring, &h->geom.telem, shm->telem, &h->telem_live, h->telemetry, h));
    STEP(
        host_bcast(&shm->telem_ring, &h->geom.telem, shm->telem, &h->telem_start, h->telemetry, h));
    STEP(host_bcast(&shm->monitor_ring, &h->geom.monitor, shm->monitor, &h->monitor_live,
                    h->monitor, h));
    STEP(host_bcast(&shm->monitor_ring, &h->geom.monitor, shm->monitor, &h->monitor_start,
                    h->monitor, h));
    STEP(host_log(h, &h->log, &shm->log_meta, &shm->log_ring, shm->log_data, sizeof shm->log_data));
    STEP(host_log(h, &h->timing, &shm->timing_meta, &shm->timing_ring, shm->timing,
                  sizeof shm->timing));
    STEP(h->doorbell = xrf_doorbell_wait(shm, h->doorbell, 0));
#undef STEP
}

static struct host host;
static struct script script;

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    reset_segment();
    parse(data, size, &script);
    for (size_t i = 0; i < script.nsetup; i++)
        apply(&script.setup[i]);

    /* Attach: a segment whose fixed rings are not as xrf_shm_init made them is refused (the
     * appliance does not run it). */
    if (xrf_shm_check(shm, sizeof(struct xrf_shm), &host.geom) != 0)
        return 0;
    contract(host.geom.telem.slots == XRF_TELEM_SLOTS &&
                 host.geom.telem.slot_size == sizeof(struct xrf_telemetry) &&
                 host.geom.monitor.slots == XRF_MONITOR_SLOTS &&
                 host.geom.monitor.slot_size == sizeof(struct xrf_monitor_line),
             "xrf_shm_check: accepted another geometry");
    /* A reader that follows live and one that starts from the oldest publication, as the
     * appliance's telemetry stream and a rerun do. */
    host.telem_live = __atomic_load_n(&shm->telem_ring.head, __ATOMIC_ACQUIRE);
    host.monitor_live = __atomic_load_n(&shm->monitor_ring.head, __ATOMIC_ACQUIRE);
    host.telem_start = host.monitor_start = 0;
    host.doorbell = __atomic_load_n(&shm->doorbell, __ATOMIC_ACQUIRE);
    host.log.taken = host.timing.taken = 0;

    struct racer racer = {&script, 0};
    pthread_t thread;
    int racing = script.nconcurrent > 0 && pthread_create(&thread, NULL, race, &racer) == 0;
    size_t next = 0;
    for (int round = 0; round < ROUNDS; round++)
        host_round(&host, round, &script, &next);
    if (racing) {
        __atomic_store_n(&racer.done, 1, __ATOMIC_RELEASE);
        pthread_join(thread, NULL);
    }
    return 0;
}

/* ---- seeds --------------------------------------------------------------------------------- */

#define U16(v) (uint8_t)(v), (uint8_t)((v) >> 8)
#define U32(v) U16(v), U16((v) >> 16)
#define U64(v) U32(v), U32((uint64_t)(v) >> 32)
#define S(kind) OPCODE(PHASE_SETUP, kind)
#define I(kind) OPCODE(PHASE_INTERLEAVED, kind)
#define C(kind) OPCODE(PHASE_CONCURRENT, kind)

static size_t field_index(const char *name)
{
    for (size_t i = 0; i < NFIELDS; i++)
        if (strcmp(fields[i].name, name) == 0)
            return i;
    fprintf(stderr, "fuzz_channels: no field %s\n", name);
    abort();
}

static int write_seed(const char *dir, const char *name, const uint8_t *bytes, size_t n)
{
    char path[4096];
    snprintf(path, sizeof path, "%s/%s", dir, name);
    FILE *f = fopen(path, "wb");
    if (f == NULL || fwrite(bytes, 1, n, f) != n || fclose(f) != 0) {
        perror(path);
        return -1;
    }
    return 0;
}

/* The seed corpus: well-formed segments, the honest loop's own races, and the attacks that broke
 * the readers before issue 26 (regressions now). */
static int write_seeds(const char *dir)
{
    const uint8_t status_seq = (uint8_t)field_index("status.seq");
    const uint8_t data_seq = (uint8_t)field_index("ros2xeno.seq");
    const uint8_t cmd_head = (uint8_t)field_index("cmd.head");
    const uint8_t telem_head = (uint8_t)field_index("telem_ring.head");
    const uint8_t log_tail = (uint8_t)field_index("log_ring.tail");
    const uint8_t log_head = (uint8_t)field_index("log_ring.head");
    const uint8_t log_slots = (uint8_t)field_index("log_ring.slots");
    const uint8_t log_slot_size = (uint8_t)field_index("log_ring.slot_size");
    const uint8_t log_generation = (uint8_t)field_index("log_meta.generation");
    const uint8_t log_nvars = (uint8_t)field_index("log_meta.nvars");
    const uint8_t monitor_slots = (uint8_t)field_index("monitor_ring.slots");
    const uint8_t monitor_slot_size = (uint8_t)field_index("monitor_ring.slot_size");
    const uint8_t monitor_head = (uint8_t)field_index("monitor_ring.head");
    /* One operation a line (clang-format would pack them into a table). */
    // clang-format off
    const uint8_t published[] = {
        S(OP_PUB_TELEM), 50,
        S(OP_PUB_MONITOR), 10,
        S(OP_LOG_PUSH), 20,
        S(OP_TIMING_PUSH), 5,
        S(OP_STATUS_BEGIN),
        S(OP_STATUS_END),
        S(OP_DOORBELL),
    };
    const uint8_t wrapped[] = {
        S(OP_PUB_TELEM), 255, S(OP_PUB_TELEM), 255, S(OP_PUB_TELEM), 255, S(OP_PUB_TELEM), 255,
        S(OP_PUB_TELEM), 255,
        S(OP_PUB_MONITOR), 255, S(OP_PUB_MONITOR), 200,
        S(OP_LOG_PUBLISH), U16(511), 100, /* 4096-byte records, 100 variables */
        S(OP_LOG_PUSH), 255, S(OP_LOG_PUSH), 255, S(OP_LOG_PUSH), 255,
        S(OP_STORE), log_tail, U64(700), /* the host took 700 of them */
        S(OP_LOG_PUSH), 200,
    };
    const uint8_t live_loop[] = {
        C(OP_PUB_TELEM), 1,
        C(OP_PUB_MONITOR), 1,
        C(OP_LOG_PUSH), 1,
        C(OP_TIMING_PUSH), 1,
        C(OP_STATUS_BEGIN),
        C(OP_SPIN), U16(50),
        C(OP_STATUS_END),
        C(OP_CMD_POLL), 4,
        C(OP_DOORBELL),
        C(OP_YIELD),
    };
    const uint8_t stalled[] = {
        /* A loop stopped mid-write: status odd, ros2xeno claimed, command ring full. */
        S(OP_STATUS_BEGIN),
        S(OP_STORE), data_seq, U64(7),
        S(OP_STORE), cmd_head, U64(XRF_CMD_SLOTS),
        S(OP_STORE), telem_head, U64(5000),
        S(OP_SLOT_SEQ), RING_TELEM, U16(3), U64(1),
    };
    const uint8_t relayout[] = {
        S(OP_LOG_PUSH), 30,
        I(OP_LOG_PUSH), 10,
        I(OP_LOG_PUBLISH), U16(63), 8, /* the logger set up again: 512-byte records */
        I(OP_LOG_PUSH), 40,
        I(OP_STATUS_BEGIN),
        I(OP_PUB_TELEM), 3,
        I(OP_STATUS_END),
        I(OP_DOORBELL),
        I(OP_STORE), status_seq, U64(2),
    };
    /* The attacks of issue 26 (holes 3 and 4) and their kin, each after the host attached:
     * they crashed or hung the readers before the geometry was taken once (xrf_shm_check). */
    const uint8_t log_geometry[] = {
        /* hole 3: a new layout generation, the log ring made huge, its head far ahead */
        S(OP_LOG_PUSH), 10,
        I(OP_STORE), log_generation, U64(9),
        I(OP_STORE), log_slots, U64(1u << 31),
        I(OP_STORE), log_slot_size, U64(0xFFFFFFF8u),
        I(OP_STORE), log_head, U64(50000000),
        I(OP_STORE), log_nvars, U64(100000),
        I(OP_LOG_PUSH), 5,
    };
    const uint8_t monitor_geometry[] = {
        /* hole 4: the monitor ring's slot size and count rewritten under a reader */
        S(OP_PUB_MONITOR), 20,
        I(OP_STORE), monitor_slot_size, U64(0xFFFFFFF8u),
        I(OP_STORE), monitor_slots, U64(1u << 31),
        I(OP_STORE), monitor_head, U64(1u << 20),
        C(OP_PUB_MONITOR), 1,
    };
    const uint8_t misaligned[] = {
        /* a slot size that is no multiple of 8 (an alignment fault on the Pi's atomics) */
        S(OP_PUB_MONITOR), 3,
        I(OP_ADD), monitor_slot_size, U32(4),
        I(OP_PUB_MONITOR), 3,
    };
    const uint8_t command_spin[] = {
        /* every command slot's seq ahead of the head: the sender once spun for ever */
        S(OP_SLOT_SEQ), RING_CMD, U16(0), U64(UINT64_MAX / 2),
        S(OP_SLOT_SEQ), RING_CMD, U16(1), U64(1000),
        S(OP_STORE), cmd_head, U64(1),
        C(OP_SLOT_SEQ), RING_CMD, U16(2), U64(5),
    };
    const uint8_t command_overflow[] = {
        /* a slot seq and a head whose difference overflows an int64 (found by the long run) */
        S(OP_STORE), cmd_head, U64((1ull << 62) + 1),
        S(OP_SLOT_SEQ), RING_CMD, U16(1), U64(1ull << 63),
    };
    const uint8_t status_flip[] = {
        /* a loop that flips its status seqlock all the time */
        C(OP_STATUS_BEGIN),
        C(OP_STATUS_END),
        C(OP_STATUS_BEGIN),
        C(OP_YIELD),
    };
    struct {
        const char *name;
        const uint8_t *bytes;
        size_t n;
    } seeds[] = {
        {"initialised", (const uint8_t *)"", 0},
        {"published", published, sizeof published},
        {"wrapped", wrapped, sizeof wrapped},
        {"live-loop", live_loop, sizeof live_loop},
        {"stalled-loop", stalled, sizeof stalled},
        {"relayout", relayout, sizeof relayout},
        {"hole3-log-geometry", log_geometry, sizeof log_geometry},
        {"hole4-monitor-geometry", monitor_geometry, sizeof monitor_geometry},
        {"misaligned-slot-size", misaligned, sizeof misaligned},
        {"command-spin", command_spin, sizeof command_spin},
        {"command-seq-overflow", command_overflow, sizeof command_overflow},
        {"status-flip", status_flip, sizeof status_flip},
    };
    // clang-format on
    for (size_t i = 0; i < sizeof seeds / sizeof seeds[0]; i++)
        if (write_seed(dir, seeds[i].name, seeds[i].bytes, seeds[i].n) != 0)
            return -1;
    return 0;
}

int LLVMFuzzerInitialize(int *argc, char ***argv)
{
    (void)argc;
    (void)argv;
    const char *seeds = getenv("XRF_FUZZ_WRITE_SEEDS");
    if (seeds != NULL)
        exit(write_seeds(seeds) == 0 ? 0 : 1);
    map_segment();
    host.status = malloc(sizeof *host.status);
    host.telemetry = malloc(sizeof *host.telemetry);
    host.monitor = malloc(sizeof *host.monitor);
    host.header = malloc(XRF_LOGFILE_HEADER_MAX);
    if (!host.status || !host.telemetry || !host.monitor || !host.header)
        abort();
    return 0;
}
