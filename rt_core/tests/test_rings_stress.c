/*
 * Two-thread stress test of the channel rings of xrf/channels.h: a producer and a consumer run
 * concurrently over each kind of ring for about a second (or 10^6 items) and the consumer checks
 * what the single-threaded property tests cannot: no torn payloads under real concurrency,
 * sequence continuity, exact loss accounting, and no loss on the SPSC ring while it has room.
 *
 * Each payload is filled with a pattern derived from its sequence number, so a slot copied while
 * the producer overwrote it shows up as a mismatch.
 *
 * Prints "N passed, 0 failed" and exits non-zero on any failure.
 */
#define _GNU_SOURCE
#include "xrf/channels.h"

#include <errno.h>
#include <inttypes.h>
#include <pthread.h>
#include <sched.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#define MAX_ITEMS 1000000u
#define MAX_SECONDS 1.0
#define PAYLOAD_WORDS 8

static int passed, failed;

#define CHECK(cond, ...)                                         \
    do {                                                         \
        if (cond) {                                              \
            passed++;                                            \
        } else {                                                 \
            failed++;                                            \
            fprintf(stderr, "FAIL %s:%d: ", __FILE__, __LINE__); \
            fprintf(stderr, __VA_ARGS__);                        \
            fputc('\n', stderr);                                 \
        }                                                        \
    } while (0)

static double now_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}

/* The word j of item n's payload: differs between neighbouring items in every word. */
static uint64_t pattern(uint64_t n, unsigned j)
{
    return (n + 1) * 0x9E3779B97F4A7C15ull ^ ((uint64_t)j << 56 | j);
}

static void fill(uint64_t *words, uint64_t n)
{
    for (unsigned j = 0; j < PAYLOAD_WORDS; j++)
        words[j] = pattern(n, j);
}

static int intact(const uint64_t *words, uint64_t n)
{
    for (unsigned j = 0; j < PAYLOAD_WORDS; j++)
        if (words[j] != pattern(n, j))
            return 0;
    return 1;
}

/* A slot of the test rings: the common header, then the patterned payload. */
struct test_slot {
    struct xrf_slot_hdr hdr;
    uint64_t words[PAYLOAD_WORDS];
};

struct ring_fixture {
    struct xrf_ring ring;
    struct test_slot *slots;
    volatile int done;       /* producer finished */
    uint64_t produced;       /* items the producer handed to the ring (incl. dropped ones) */
    uint64_t producer_nulls; /* SPSC: begin() calls that found the ring full */
    int retry_when_full;     /* SPSC: producer waits for room instead of dropping */
};

static void *alloc_slots(uint32_t n)
{
    void *p = NULL;
    if (posix_memalign(&p, 64, (size_t)n * sizeof(struct test_slot)) != 0)
        abort();
    memset(p, 0, (size_t)n * sizeof(struct test_slot));
    return p;
}

/* ---- broadcast ring ------------------------------------------------------------------------ */

static void *bcast_producer(void *arg)
{
    struct ring_fixture *f = arg;
    double t_end = now_s() + MAX_SECONDS;
    uint64_t n = 0;
    for (; n < MAX_ITEMS && (n & 1023 || now_s() < t_end); n++) {
        struct test_slot *s = xrf_bcast_begin(&f->ring, f->slots);
        s->hdr.cycle = n;
        fill(s->words, n);
        xrf_bcast_commit(&f->ring, s);
        /* Pace the producer a little so the reader both keeps up at times and gets lapped. */
        for (volatile int spin = 0; spin < (int)(n & 127); spin++)
            ;
    }
    f->produced = n;
    __atomic_store_n(&f->done, 1, __ATOMIC_RELEASE);
    return NULL;
}

static void test_broadcast(void)
{
    struct ring_fixture f = {0};
    f.slots = alloc_slots(64);
    xrf_ring_init(&f.ring, 64, sizeof(struct test_slot));
    pthread_t producer;
    pthread_create(&producer, NULL, bcast_producer, &f);

    uint64_t cursor = 0, lost = 0, got = 0, torn = 0, gaps_unaccounted = 0, expected = 0;
    struct test_slot out;
    struct xrf_ring_geom geom;
    CHECK(xrf_ring_geom_check(&f.ring, 64, sizeof(struct test_slot), 64 * sizeof(struct test_slot),
                              &geom) == 0,
          "broadcast: geometry refused");
    for (;;) {
        int finished = __atomic_load_n(&f.done, __ATOMIC_ACQUIRE);
        uint64_t lost_before = lost;
        if (xrf_bcast_read_g(&f.ring, &geom, f.slots, &cursor, &out, &lost) == 1) {
            got++;
            if (!intact(out.words, out.hdr.cycle))
                torn++;
            /* Continuity: the item is the next one after the last, plus exactly what was lost. */
            if (out.hdr.cycle != expected + (lost - lost_before))
                gaps_unaccounted++;
            expected = out.hdr.cycle + 1;
        } else if (finished) {
            break;
        }
    }
    pthread_join(producer, NULL);
    CHECK(torn == 0, "broadcast: %" PRIu64 " torn payloads", torn);
    CHECK(gaps_unaccounted == 0, "broadcast: %" PRIu64 " gaps not counted as lost",
          gaps_unaccounted);
    CHECK(got + lost == f.produced,
          "broadcast: read %" PRIu64 " + lost %" PRIu64 " != published %" PRIu64, got, lost,
          f.produced);
    CHECK(cursor == f.produced, "broadcast: cursor %" PRIu64 " != head %" PRIu64, cursor,
          f.produced);
    printf("broadcast: %" PRIu64 " published, %" PRIu64 " read, %" PRIu64 " lost\n", f.produced,
           got, lost);
    free(f.slots);
}

/* ---- SPSC ring ----------------------------------------------------------------------------- */

static void *spsc_producer(void *arg)
{
    struct ring_fixture *f = arg;
    double t_end = now_s() + MAX_SECONDS;
    uint64_t n = 0;
    for (; n < MAX_ITEMS && (n & 1023 || now_s() < t_end); n++) {
        struct test_slot *s;
        while ((s = xrf_spsc_begin(&f->ring, f->slots)) == NULL) {
            f->producer_nulls++;
            if (!f->retry_when_full)
                break;
            sched_yield();
        }
        if (!s)
            continue; /* dropped, as the loop drops a log record */
        s->hdr.seq = n;
        fill(s->words, n);
        xrf_spsc_commit(&f->ring, s);
    }
    f->produced = n;
    __atomic_store_n(&f->done, 1, __ATOMIC_RELEASE);
    return NULL;
}

static void test_spsc(int retry_when_full)
{
    const char *mode = retry_when_full ? "spsc (producer waits)" : "spsc (producer drops)";
    struct ring_fixture f = {0};
    f.retry_when_full = retry_when_full;
    f.slots = alloc_slots(256);
    xrf_ring_init(&f.ring, 256, sizeof(struct test_slot));
    pthread_t producer;
    pthread_create(&producer, NULL, spsc_producer, &f);

    uint64_t got = 0, torn = 0, out_of_order = 0, skipped = 0, next = 0, consumed = 0;
    uint64_t tail = 0;
    struct xrf_ring_geom geom;
    CHECK(xrf_ring_geom_check(&f.ring, 256, sizeof(struct test_slot),
                              256 * sizeof(struct test_slot), &geom) == 0,
          "%s: geometry refused", mode);
    for (;;) {
        int finished = __atomic_load_n(&f.done, __ATOMIC_ACQUIRE);
        const void *first = NULL;
        int ready = xrf_spsc_peek_run_g(&f.ring, &geom, f.slots, tail, &first);
        if (ready < 0) {
            CHECK(0, "%s: peek refused a sound ring (%d)", mode, ready);
            break;
        }
        const struct test_slot *s = ready > 0 ? first : NULL;
        if (!s) {
            if (finished)
                break;
            /* Consume slowly now and then, so that the ring does fill up. */
            continue;
        }
        struct test_slot copy = *s;
        xrf_spsc_release_g(&f.ring, &tail, 1);
        got++;
        if (!intact(copy.words, copy.hdr.seq))
            torn++;
        if (copy.hdr.seq < next)
            out_of_order++;
        else
            skipped += copy.hdr.seq - next;
        next = copy.hdr.seq + 1;
        if ((++consumed & 4095) == 0)
            for (volatile int spin = 0; spin < 200000; spin++)
                ;
    }
    pthread_join(producer, NULL);
    skipped += f.produced - next; /* records dropped after the last one that arrived */
    uint64_t dropped = __atomic_load_n(&f.ring.dropped, __ATOMIC_ACQUIRE);
    CHECK(torn == 0, "%s: %" PRIu64 " torn payloads", mode, torn);
    CHECK(out_of_order == 0, "%s: %" PRIu64 " records out of order", mode, out_of_order);
    CHECK(dropped == f.producer_nulls, "%s: dropped %" PRIu64 " != full begins %" PRIu64, mode,
          dropped, f.producer_nulls);
    if (retry_when_full) {
        CHECK(got == f.produced && skipped == 0,
              "%s: %" PRIu64 " of %" PRIu64 " arrived, %" PRIu64 " skipped", mode, got, f.produced,
              skipped);
    } else {
        /* Every missing record is one the producer was told it could not store. */
        CHECK(got + dropped == f.produced && skipped == dropped,
              "%s: got %" PRIu64 " + dropped %" PRIu64 " != %" PRIu64 " (skipped %" PRIu64 ")",
              mode, got, dropped, f.produced, skipped);
    }
    printf("%s: %" PRIu64 " produced, %" PRIu64 " consumed, %" PRIu64 " found the ring full\n",
           mode, f.produced, got, dropped);
    free(f.slots);
}

/* ---- command ring: two producers, one consumer --------------------------------------------- */

#define CMD_PRODUCERS 2
#define CMD_ITEMS 200000u

struct cmd_fixture {
    struct xrf_shm *shm;
    volatile int done[CMD_PRODUCERS];
    uint32_t sent[CMD_PRODUCERS];
    uint64_t full;
};

struct cmd_producer_arg {
    struct cmd_fixture *f;
    int id;
};

static void *cmd_producer(void *p)
{
    struct cmd_producer_arg *a = p;
    double t_end = now_s() + MAX_SECONDS;
    uint32_t k = 0;
    for (; k < CMD_ITEMS && (k & 1023 || now_s() < t_end); k++) {
        /* t_sent_ns carries a check value so a torn slot (cmd of one, time of another) shows. */
        while (xrf_cmd_send(&a->f->shm->cmd, (int32_t)k, a->id, (int64_t)k * 7 + a->id) ==
               -EAGAIN) {
            __atomic_add_fetch(&a->f->full, 1, __ATOMIC_RELAXED);
            sched_yield();
        }
    }
    a->f->sent[a->id] = k;
    __atomic_store_n(&a->f->done[a->id], 1, __ATOMIC_RELEASE);
    return NULL;
}

static void test_commands(void)
{
    struct cmd_fixture f = {0};
    f.shm = calloc(1, sizeof *f.shm);
    if (!f.shm)
        abort();
    xrf_shm_init(f.shm);
    pthread_t threads[CMD_PRODUCERS];
    struct cmd_producer_arg args[CMD_PRODUCERS];
    for (int i = 0; i < CMD_PRODUCERS; i++) {
        args[i] = (struct cmd_producer_arg){&f, i};
        pthread_create(&threads[i], NULL, cmd_producer, &args[i]);
    }
    uint64_t got = 0, bad_ticket = 0, bad_order = 0, torn = 0, last_ticket = 0;
    int64_t next_cmd[CMD_PRODUCERS] = {0};
    struct xrf_cmd_slot slot;
    for (;;) {
        int all_done = 1;
        for (int i = 0; i < CMD_PRODUCERS; i++)
            all_done &= __atomic_load_n(&f.done[i], __ATOMIC_ACQUIRE);
        if (!xrf_cmd_poll(&f.shm->cmd, &slot)) {
            if (all_done)
                break;
            continue;
        }
        got++;
        if (slot.ticket != last_ticket + 1)
            bad_ticket++;
        last_ticket = slot.ticket;
        if (slot.source < 0 || slot.source >= CMD_PRODUCERS ||
            slot.t_sent_ns != (int64_t)slot.cmd * 7 + slot.source) {
            torn++;
            continue;
        }
        if (slot.cmd != next_cmd[slot.source])
            bad_order++;
        next_cmd[slot.source] = slot.cmd + 1;
    }
    for (int i = 0; i < CMD_PRODUCERS; i++)
        pthread_join(threads[i], NULL);
    uint64_t sent = 0;
    for (int i = 0; i < CMD_PRODUCERS; i++)
        sent += f.sent[i];
    CHECK(got == sent, "commands: %" PRIu64 " of %" PRIu64 " arrived", got, sent);
    CHECK(bad_ticket == 0, "commands: %" PRIu64 " tickets out of sequence", bad_ticket);
    CHECK(bad_order == 0, "commands: %" PRIu64 " out of FIFO order within a producer", bad_order);
    CHECK(torn == 0, "commands: %" PRIu64 " torn slots", torn);
    printf("commands: %" PRIu64 " sent by %d producers, %" PRIu64 " received, ring full %" PRIu64
           " times\n",
           sent, CMD_PRODUCERS, got, f.full);
    free(f.shm);
}

/* ---- Ros2Xeno latest-wins buffer and the status seqlock ------------------------------------ */

struct data_fixture {
    struct xrf_shm *shm;
    volatile int done;
    uint64_t written;
};

static void *data_writer(void *p)
{
    struct data_fixture *f = p;
    double t_end = now_s() + MAX_SECONDS;
    uint64_t words[PAYLOAD_WORDS];
    uint64_t n = 0;
    for (; n < MAX_ITEMS && (n & 1023 || now_s() < t_end); n++) {
        fill(words, n);
        xrf_data_in_write(&f->shm->ros2xeno, words, sizeof words, (int64_t)n);
        /* The loop's status block under its seqlock, written the same way the engine does. */
        xrf_status_write_begin(&f->shm->status);
        f->shm->status.cycles = n;
        f->shm->status.missed = n * 3;
        snprintf(f->shm->status.reject_reason, sizeof f->shm->status.reject_reason, "%" PRIu64, n);
        xrf_status_write_end(&f->shm->status);
        /* Leave readers windows between writes, as a loop's cycle does. */
        for (volatile int spin = 0; spin < (int)(n & 255); spin++)
            ;
    }
    f->written = n;
    __atomic_store_n(&f->done, 1, __ATOMIC_RELEASE);
    return NULL;
}

static void test_data_in_and_status(void)
{
    struct data_fixture f = {0};
    f.shm = calloc(1, sizeof *f.shm);
    if (!f.shm)
        abort();
    xrf_shm_init(f.shm);
    pthread_t writer;
    pthread_create(&writer, NULL, data_writer, &f);
    uint32_t last_seq = 0;
    uint64_t words[PAYLOAD_WORDS], reads = 0, torn = 0, backwards = 0, status_reads = 0,
                                   status_torn = 0;
    int64_t last_t = -1, t_sent = 0;
    struct xrf_status *status = malloc(sizeof *status);
    for (;;) {
        int finished = __atomic_load_n(&f.done, __ATOMIC_ACQUIRE);
        if (xrf_data_in_try_read(&f.shm->ros2xeno, &last_seq, words, sizeof words, &t_sent)) {
            reads++;
            if (!intact(words, (uint64_t)t_sent))
                torn++;
            if (t_sent <= last_t)
                backwards++;
            last_t = t_sent;
        }
        if (xrf_status_read(&f.shm->status, status) == 0) {
            char expect[32];
            snprintf(expect, sizeof expect, "%" PRIu64, status->cycles);
            status_reads++;
            if (status->missed != status->cycles * 3 ||
                (status->cycles && strcmp(expect, status->reject_reason) != 0))
                status_torn++;
        }
        if (finished)
            break;
    }
    pthread_join(writer, NULL);
    CHECK(reads > 0 && torn == 0, "ros2xeno: %" PRIu64 " torn of %" PRIu64 " reads", torn, reads);
    CHECK(backwards == 0, "ros2xeno: %" PRIu64 " reads went back in time", backwards);
    CHECK(status_reads > 0 && status_torn == 0, "status: %" PRIu64 " torn of %" PRIu64 " reads",
          status_torn, status_reads);
    printf("ros2xeno/status: %" PRIu64 " writes, %" PRIu64 " fresh reads, %" PRIu64
           " status reads\n",
           f.written, reads, status_reads);
    free(status);
    free(f.shm);
}

/* ---- doorbell ------------------------------------------------------------------------------ */

/* The loop's side (xrf_doorbell_should_ring, then a wake when someone waits) against a host that
 * waits for each new value. A wake lost between the two (the store-then-load race the SEQ_CST
 * accesses exclude) leaves the host asleep for its whole timeout while the bell moved: counted,
 * and none may happen. The timeout is a bound on failure: the bell rings far more often. x86
 * rarely shows the lost wake at run time; under ThreadSanitizer (test_tsan.py) the accesses'
 * orderings are what is checked. */
#define BELLS 20000u
#define BELL_WAIT_MS 5000

struct bell_fixture {
    struct xrf_shm *shm;
    uint64_t woken; /* wakes sent (should_ring said someone waits) */
};

static void *bell_ringer(void *p)
{
    struct bell_fixture *f = p;
    for (uint32_t i = 0; i < BELLS; i++) {
        if (xrf_doorbell_should_ring(f->shm)) {
            xrf_doorbell_wake(f->shm);
            f->woken++;
        }
        for (volatile int spin = 0; spin < (int)(i & 1023); spin++)
            ;
    }
    return NULL;
}

static void test_doorbell(void)
{
    struct bell_fixture f = {0};
    f.shm = calloc(1, sizeof *f.shm);
    if (!f.shm)
        abort();
    xrf_shm_init(f.shm);
    pthread_t ringer;
    uint32_t seen = xrf_doorbell_wait(f.shm, UINT32_MAX, 0); /* the current value, no sleep */
    pthread_create(&ringer, NULL, bell_ringer, &f);
    uint64_t waits = 0, slept_through = 0;
    while (seen != BELLS) {
        double t0 = now_s();
        uint32_t now = xrf_doorbell_wait(f.shm, seen, BELL_WAIT_MS);
        waits++;
        /* A lost wake: the bell moved while this host slept (FUTEX_WAIT compares the word, so
         * the move came after it fell asleep) and nobody woke it: it sleeps the whole timeout
         * and returns the new value. The ringer rings every few microseconds, so a full
         * timeout that ends on a changed bell is the lost wake, not a quiet ringer. */
        if (now != seen && now_s() - t0 >= BELL_WAIT_MS * 1e-3 * 0.9)
            slept_through++;
        seen = now;
    }
    pthread_join(ringer, NULL);
    CHECK(seen == BELLS, "doorbell: ended at %u of %u", seen, BELLS);
    CHECK(slept_through == 0, "doorbell: %" PRIu64 " waits slept through a ring", slept_through);
    CHECK(__atomic_load_n(&f.shm->doorbell_waiters, __ATOMIC_SEQ_CST) == 0,
          "doorbell: waiters count left at %u", f.shm->doorbell_waiters);
    printf("doorbell: %u rings, %" PRIu64 " waits, %" PRIu64 " wakes sent\n", BELLS, waits,
           f.woken);
    free(f.shm);
}

int main(void)
{
    test_broadcast();
    test_spsc(1);
    test_spsc(0);
    test_commands();
    test_data_in_and_status();
    test_doorbell();
    printf("%d passed, %d failed\n", passed, failed);
    return failed ? 1 : 0;
}
