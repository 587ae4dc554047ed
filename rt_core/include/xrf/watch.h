/*
 * xrf/watch.h — the safety watcher: a small thread beside a loop process that puts the outputs in
 * a safe state the moment the loop is gone or hung, whatever the process that started it is doing.
 *
 * It is started by the host that supervises a run (the appliance, through the cffi binding) and
 * never needs that host again until it has acted: it is woken by the kernel (a pidfd turns
 * readable when the loop process exits), checks the loop's heartbeat in the shared memory on a
 * short timer, and runs at a real-time priority above any the run may take, off the run's CPUs,
 * when it may. On exit or hang it
 *   1. forces the outputs safe: the simulated board's forced_off flag and/or an FPGA RESET frame
 *      over spidev (xrf_ico_frame_op + the spidev transport: the one C implementation),
 *   2. on a hang, kills the loop (pidfd_send_signal, so no pid can be reused under it),
 *   3. only then writes the notify descriptor (an eventfd the host's event loop reads).
 * Nothing in the host (a busy asyncio loop, a garbage-collection pause, the GIL) sits between the
 * exit and the safe outputs.
 *
 * API style as libevl: xrf_ prefix, 0 or -errno.
 */
#ifndef XRF_WATCH_H
#define XRF_WATCH_H

#include <stdint.h>

#include "xrf/channels.h"

#ifdef __cplusplus
extern "C" {
#endif

/* cffi-begin */
#define XRF_WATCH_WATCHING 0  /* nothing happened yet */
#define XRF_WATCH_EXIT 1      /* the loop process ended */
#define XRF_WATCH_HANG 2      /* alive but no cycle for longer than hang_timeout_ns: killed */
#define XRF_WATCH_CANCELLED 3 /* xrf_watch_stop() before anything happened */

#define XRF_WATCH_RESET_NOT_TRIED 1 /* reset_status: no spidev configured */

struct xrf_watch_config {
    int pid;                 /* the loop process, as this process sees it */
    int64_t hang_timeout_ns; /* no new heartbeat for this long while running = hung; 0: off */
    int64_t check_ns;        /* heartbeat check period */
    int rt_priority;         /* SCHED_FIFO priority for the watcher; 0: leave it SCHED_OTHER */
    int force_sim;           /* set the simulated board's forced_off (and zero its outputs) */
    char spi_device[64];     /* "" or the spidev the FPGA RESET frame goes to */
    uint32_t spi_speed_hz;
    int notify_fd; /* -1 or an eventfd written once the outputs are safe */
    /* CPUs (bit n = CPU n, n < 64) the watcher keeps off: the run's own, where its threads may
     * spin at a real-time priority. Ignored when no other CPU is allowed to the watcher. */
    uint64_t avoid_cpus;
};

struct xrf_watch_result {
    int32_t reason;       /* XRF_WATCH_* */
    int32_t sim_forced;   /* 1: forced_off was set */
    int32_t reset_status; /* FPGA RESET: 0 sent, -errno failed, XRF_WATCH_RESET_NOT_TRIED */
    int32_t rt_status;    /* 0: running at SCHED_FIFO rt_priority; -errno: it was refused */
    int32_t kill_status;  /* hang: 0 killed, -errno otherwise */
    int32_t pad;
    int64_t event_ns;     /* CLOCK_MONOTONIC when the exit or hang was seen */
    int64_t safe_ns;      /* CLOCK_MONOTONIC when the outputs were safe */
    int64_t heartbeat_ns; /* the loop's last heartbeat (start of its last cycle) */
};

struct xrf_watch;

/* Start watching `pid` whose shared memory is `shm` (may be NULL: exit watching only, nothing to
 * force in memory). The mapping must outlive the watcher (stop it before unmapping). */
int xrf_watch_start(struct xrf_shm *shm, const struct xrf_watch_config *cfg,
                    struct xrf_watch **out);
/* Copy the result so far; returns its reason (XRF_WATCH_WATCHING while still watching). */
int xrf_watch_result(struct xrf_watch *w, struct xrf_watch_result *out);
/* End the watcher and free it. A loop that has already exited is still handled (outputs made
 * safe) before the thread ends, so the final result never misses an exit. */
int xrf_watch_stop(struct xrf_watch *w, struct xrf_watch_result *out);
/* Send the FPGA RESET frame once over spidev `device` (also what the watcher does). */
int xrf_fpga_reset(const char *device, uint32_t speed_hz);
/* cffi-end */

#ifdef __cplusplus
}
#endif

#endif /* XRF_WATCH_H */
