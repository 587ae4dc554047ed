/*
 * virtual backend: simulated time (XRF_VIRTUAL_TIME, simulated board only; see
 * docs/rt_core/runtime.md "Simulated time"). The loop never sleeps: the clock it reads is the
 * loop thread's CPU time plus an offset, and "sleeping until the next deadline" moves the offset
 * so the clock reads exactly that deadline. The time a cycle computes passes as it costs (cycle
 * times and overruns are the controller's own; time the machine gave to others is not counted);
 * only the idle rest of each period is skipped. The simulated board reads the same clock (xrf_sim_set_clock), so the plant advances
 * by the same dt as in real time.
 *
 * It waits only for its consumers: while the host holds it (xrf_vtime.run_until) or while the
 * log ring is more than half full (the log must not lose records because the loop runs fast).
 * Those waits are 100 us naps: nothing real-time is at stake, and it spares the machine's cores.
 */
#define _GNU_SOURCE
#include "xrf/backend.h"

#include <pthread.h>
#include <sched.h>
#include <signal.h>
#include <stdio.h>
#include <string.h>
#include <sys/mman.h>
#include <time.h>

/* One loop thread per process: the backend's state is the process's. */
static int64_t vt_offset_ns;           /* the loop's clock minus CLOCK_MONOTONIC; only grows */
static struct xrf_shm *vt_shm;         /* xrf_backend_virtual_bind */
static volatile sig_atomic_t *vt_stop; /* the runtime's SIGINT/SIGTERM flag */

int64_t xrf_virtual_real_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts); /* vDSO: no system call */
    return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

/* The loop thread's CPU time: what its own computing took, not what a busy machine made it
 * wait (a preempted cycle must not look late in a simulation). A system call, unlike
 * CLOCK_MONOTONIC; simulated time is not the firm real-time path. */
static int64_t cpu_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
    return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

static int64_t virtual_now_ns(void)
{
    return cpu_ns() + vt_offset_ns;
}

int64_t xrf_virtual_now_ns(void)
{
    return virtual_now_ns();
}

/* The host attached and stopped beating: let the loop cycle so its host-lost action runs. */
static int host_gone(const struct xrf_shm *shm, int64_t real_ns)
{
    uint32_t timeout_ms = __atomic_load_n(&shm->host_timeout_ms, __ATOMIC_RELAXED);
    int64_t hb = __atomic_load_n(&shm->host_heartbeat_ns, __ATOMIC_RELAXED);
    return timeout_ms > 0 && hb != 0 && real_ns - hb > (int64_t)timeout_ms * 1000000LL;
}

static int must_wait(const struct xrf_shm *shm)
{
    const uint64_t until = __atomic_load_n(&shm->vtime.run_until, __ATOMIC_ACQUIRE);
    /* A command sent to a held loop is taken at once: one more cycle per command (the host's
     * wait for its answer needs no step of its own, and the cycle it lands in is still exact). */
    const int command_waiting = __atomic_load_n(&shm->cmd.head, __ATOMIC_ACQUIRE) != shm->cmd.tail;
    if (shm->status.cycles >= until && !command_waiting) /* status.cycles: this thread's own */
        return 1;
    const uint32_t slots = shm->log_ring.slots; /* set by this process's logger */
    const uint64_t head = shm->log_ring.head;
    const uint64_t tail = __atomic_load_n(&shm->log_ring.tail, __ATOMIC_ACQUIRE);
    return slots > 0 && head - tail > slots / 2;
}

static int virtual_sleep_until(int64_t abs_ns)
{
    struct xrf_shm *shm = vt_shm;
    if (shm != NULL) {
        int64_t real = xrf_virtual_real_ns();
        int64_t waited_from = 0;
        while (must_wait(shm) && !(vt_stop && *vt_stop) && !host_gone(shm, real)) {
            /* The watchdog compares the heartbeat with its own real clock: a held loop is alive. */
            __atomic_store_n(&shm->status.heartbeat_ns, real, __ATOMIC_RELAXED);
            if (waited_from == 0)
                waited_from = cpu_ns();
            struct timespec nap = {0, 100 * 1000};
            nanosleep(&nap, NULL);
            real = xrf_virtual_real_ns();
        }
        /* The status block's heartbeat holds the loop's clock, ahead of the real one: put the
         * real time there, or the watchdog would see a hung loop as alive until real time caught
         * up. A single aligned store beside the seqlock: a reader gets either value. */
        __atomic_store_n(&shm->status.heartbeat_ns, real, __ATOMIC_RELAXED);
        /* Waiting for the host or the log writer is not the controller's time (the naps' own
         * system calls cost CPU time). */
        if (waited_from != 0)
            vt_offset_ns -= cpu_ns() - waited_from;
    }
    const int64_t now = virtual_now_ns();
    if (abs_ns > now)
        vt_offset_ns += abs_ns - now; /* wake exactly on the deadline */
    return 0;
}

static void virtual_ring_doorbell(struct xrf_shm *shm)
{
    xrf_doorbell_wake(shm);
}

static uint64_t virtual_demotions(void)
{
    return 0;
}

static int virtual_thread_setup(const struct xrf_rt_config *cfg, int *rt_sched)
{
    *rt_sched = 0;
    /* A loop that never sleeps must not hold a real-time priority: it would starve the machine.
     * An XRF2 main may have made this thread SCHED_FIFO already: undo that. */
    struct sched_param sp;
    memset(&sp, 0, sizeof sp);
    int r = pthread_setschedparam(pthread_self(), SCHED_OTHER, &sp);
    if (r != 0)
        fprintf(stderr, "xrf: warning: simulated time: cannot leave real-time scheduling: %s\n",
                strerror(r));
    if (cfg->cpu >= 0) {
        cpu_set_t set;
        CPU_ZERO(&set);
        CPU_SET(cfg->cpu, &set);
        pthread_setaffinity_np(pthread_self(), sizeof set, &set);
    }
    if (cfg->lock_memory)
        mlockall(MCL_CURRENT | MCL_FUTURE); /* page faults cost time, not correctness, here */
    vt_offset_ns = xrf_virtual_real_ns() - cpu_ns(); /* starts at the real time, then its own */
    return 0;
}

static void virtual_thread_teardown(void)
{
    vt_shm = NULL;
}

static const struct xrf_backend virtual_backend = {
    .name = "virtual",
    .thread_setup = virtual_thread_setup,
    .now_ns = virtual_now_ns,
    .sleep_until = virtual_sleep_until,
    .ring_doorbell = virtual_ring_doorbell,
    .demotions = virtual_demotions,
    .thread_teardown = virtual_thread_teardown,
};

const struct xrf_backend *xrf_backend_virtual(void)
{
    return &virtual_backend;
}

void xrf_backend_virtual_bind(struct xrf_shm *shm, volatile sig_atomic_t *stop)
{
    vt_shm = shm;
    vt_stop = stop;
}
