/*
 * xrf/watch.h — the safety watcher: a small thread beside a loop process that puts the outputs in
 * a safe state the moment the loop is gone or hung, whatever the process that started it is doing.
 *
 * It is started by the host that supervises a run (the appliance, through the cffi binding) and
 * never needs that host again until it has acted: it is woken by the kernel (a pidfd turns
 * readable when the loop process exits), checks the loop's heartbeat in the shared memory on a
 * short timer, and runs at a real-time priority above any the run may take, off the run's CPUs,
 * when it may. On exit or hang it
 *   1. forces the outputs safe, as the bench's safe reaction says (XRF_SAFE_REACTIONS, from the
 *      bench profile): the simulated board's forced_off flag and/or a frame over spidev (an FPGA
 *      RESET, or for `brake` an ALL frame with the brake output on: xrf/ico.h's frame builders +
 *      the spidev transport, the one C implementation of each),
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
#define XRF_WATCH_WATCHING 0   /* nothing happened yet */
#define XRF_WATCH_EXIT 1       /* the loop process ended */
#define XRF_WATCH_HANG 2       /* alive but no cycle for longer than hang_timeout_ns: killed */
#define XRF_WATCH_CANCELLED 3  /* xrf_watch_stop() before anything happened */
#define XRF_WATCH_HOST_GONE 4  /* the host (host_pid) died first: the loop was killed, made safe */
#define XRF_WATCH_LOOP_ENDED 5 /* host_only: the loop ended first, left to the host's watcher */

#define XRF_WATCH_RESET_NOT_TRIED 1 /* reset_status: no spidev configured */
/* A hang's diagnosis (xrf_watch_diagnosis): where the loop process's threads were when the hang
 * was declared, read from /proc before the kill. At most this many bytes and threads. */
#define XRF_WATCH_DIAG_BYTES 49152
#define XRF_WATCH_DIAG_TASKS 16
/* Its records, one after the other: struct xrf_watch_diag_rec then `len` bytes as /proc gave
 * them (the guest's text among them: its threads' names). Kinds: */
/* META, tid 0: "t0 t1 t2 heartbeat": CLOCK_MONOTONIC ns at the first pass, at the second
 * schedstat pass and at the end; the loop's last heartbeat. */
#define XRF_DIAG_META 1
#define XRF_DIAG_STAT 2       /* /proc/PID/task/TID/stat */
#define XRF_DIAG_STATUS 3     /* .../status */
#define XRF_DIAG_WCHAN 4      /* .../wchan */
#define XRF_DIAG_SYSCALL 5    /* .../syscall ("running" while on a CPU) */
#define XRF_DIAG_SCHEDSTAT 6  /* .../schedstat: ns on CPU, ns waiting for one, slices */
#define XRF_DIAG_STACK 7      /* .../stack (root only) */
#define XRF_DIAG_SCHEDSTAT2 8 /* schedstat again, 10 ms later: running, waiting or asleep */
#define XRF_DIAG_CGROUP 9     /* /proc/PID/cgroup; tid 0 */
/* The stat of a task of another process that was runnable (state R) at a real-time policy: who
 * may have held the loop's CPU (another program's real-time thread). At most
 * XRF_WATCH_DIAG_OTHERS of them, from a scan of at most XRF_WATCH_DIAG_SCAN tasks. */
#define XRF_DIAG_OTHER 10
#define XRF_DIAG_OTHER_SCHEDSTAT 11  /* such a task's schedstat, at the first look */
#define XRF_DIAG_OTHER_SCHEDSTAT2 12 /* and at the second */
#define XRF_WATCH_DIAG_OTHERS 16
#define XRF_WATCH_DIAG_SCAN 4096
struct xrf_watch_diag_rec {
    uint16_t kind;
    uint16_t len;
    int32_t tid;
};
/* spi_device: up to XRF_MAX_BOARDS device paths, comma-separated (xrf_spidev_open). */
#define XRF_WATCH_SPI_MAX 400
/* hold on a real bench: how far (rad) past a joint's limit a pose from the counts may read
 * (a joint pressed on its stop, the stop's give) before it is not believed. */
#define XRF_WATCH_POSE_MARGIN_DEG 5
/* hold on a real bench: the encoder sampling period while watching (ns): the counters are
 * 14 bits, so the watcher follows their wraps from the run's start (xrf/hold.h max_speed). */
#define XRF_WATCH_SAMPLE_NS 2000000

struct xrf_ico_transport; /* xrf/ico.h */

/* What "safe" is for a bench (its profile's safety.reaction), done by the watcher on an exit or
 * a hang: X(NAME, "name", number). Hosts name them from here (xrf_safe_reaction_name/parse,
 * Python's channels.SAFE_REACTIONS, the profile's validation); the numbers are the config's.
 *  zero:  every PWM and digital output zero (an FPGA RESET): right for a robot that stays where
 *         it is unpowered (RELbot, Jiwy, a lead-screw stage).
 *  brake: every PWM zero and the brake's digital output (brake_channel) on, and kept on: a
 *         robot whose brake holds it once engaged. The output is never switched off by the
 *         watcher, so a brake wired either way (energise-to-engage) stays engaged.
 *  hold:  a gravity-loaded arm (the youBot): the watcher runs a fallback law (xrf/hold.h) that
 *         holds the pose measured at the fault with gravity compensation and damping, then
 *         lowers the arm at a bounded speed to its rest pose on its hard stops, then zero. On the
 *         simulated board the watcher steps the plant itself from the board's snapshot in the
 *         shared memory (nothing else does once the loop is gone): `plant` names it. */
#define XRF_SAFE_REACTIONS(X) \
    X(ZERO, "zero", 0)        \
    X(BRAKE, "brake", 1)      \
    X(HOLD, "hold", 2)

struct xrf_watch_config {
    int pid;                 /* the loop process, as this process sees it */
    int64_t hang_timeout_ns; /* no new heartbeat for this long while running = hung; 0: off */
    int64_t check_ns;        /* heartbeat check period */
    int rt_priority;         /* SCHED_FIFO priority for the watcher; 0: leave it SCHED_OTHER */
    int force_sim;           /* set the simulated board's forced_off (and zero its outputs) */
    /* "" or the bench's spidev devices, one per ico board, comma-separated, board 1 first:
     * where the safe frames (every board's) and a real bench's `hold` go. */
    char spi_device[XRF_WATCH_SPI_MAX];
    uint32_t spi_speed_hz;
    int notify_fd; /* -1 or an eventfd written once the outputs are safe */
    /* CPUs (bit n = CPU n, n < 64) the watcher keeps off: the run's own, where its threads may
     * spin at a real-time priority. Ignored when no other CPU is allowed to the watcher. */
    uint64_t avoid_cpus;
    int32_t safe_reaction; /* XRF_SAFE_REACTION_* (0: zero) */
    int32_t brake_channel; /* brake: the channel (1..4) whose digital output engages the brake */
    int32_t plant;         /* hold: the plant table's id (xrf/plants.h) of the simulated arm */
    /* > 0: also watch this process (the appliance that supervises the run). If it dies first,
     * the loop is killed (it would run on unsupervised) and the outputs made safe as on an exit:
     * for `hold`, the arm is held and lowered. */
    int32_t host_pid;
    /* 1: act only on the host's death; a loop that ends first is the host's own watcher's to
     * handle (XRF_WATCH_LOOP_ENDED, nothing done). The per-run `xrf-watch` process runs so. */
    int32_t host_only;
    /* hold on a real bench (spi_device or xrf_watch_start_on's transport; force_sim 0): the arm
     * model is plant's (`arm`, plant.h), its pose counted from the counts read at start, when
     * the bench guarantees the arm parked at its `zero` pose (docs/developers/safety.md). From
     * the bench profile: the joints' encoder counts per motor revolution, the channels whose
     * encoder counts down as the joint turns positive (encoder.inverted) and those a positive
     * PWM turns the counts down (direction -1): bit n = channel n + 1. */
    int32_t enc_counts_per_rev;
    uint32_t enc_inverted;
    uint32_t pwm_reversed;
    int32_t pad;
    /* > 0: the watcher also writes the segment's host heartbeat (host_heartbeat_ns) this often,
     * as long as the host said it was alive (xrf_watch_host_alive) within host_grace_ns. The
     * loop's host timeout then means "the appliance process is gone" (this thread dies with it),
     * and a busy machine that starves the appliance's event loop for a second (a browser
     * starting on a 2-core lab PC) does not pause the run; an event loop stuck for longer than
     * the grace still does. 0: the host beats alone (the per-run xrf-watch process: host_only). */
    int64_t host_beat_ns;
    int64_t host_grace_ns;
};

struct xrf_watch_result {
    int32_t reason;       /* XRF_WATCH_* */
    int32_t sim_forced;   /* 1: forced_off was set */
    int32_t reset_status; /* FPGA RESET: 0 sent, -errno failed, XRF_WATCH_RESET_NOT_TRIED */
    int32_t rt_status;    /* 0: running at SCHED_FIFO rt_priority; -errno: it was refused */
    int32_t kill_status;  /* hang: 0 killed, -errno otherwise */
    /* A real bench's hold_status -ETIME or -EPROTO: the time between the two count samples the
     * failed check compared (µs), so a watcher thread kept off the CPU (-ETIME after a long gap)
     * is told apart from a counter that jumped (-EPROTO after 2 ms). 0: no such failure. */
    int32_t hold_gap_us;
    int64_t event_ns;     /* CLOCK_MONOTONIC when the exit or hang was seen */
    int64_t safe_ns;      /* CLOCK_MONOTONIC when the outputs were safe */
    int64_t heartbeat_ns; /* the loop's last heartbeat (start of its last cycle) */
    /* hold: CLOCK_MONOTONIC when the arm was at rest and the outputs zero (0: not yet), the
     * largest distance of a joint from the law's reference until then (µrad), the law's phase
     * (XRF_HOLD_PHASE_*, 0 before it started), and 0 or -errno, when the watcher zeroed the
     * outputs instead of holding (or stopped holding): -EOPNOTSUPP a real bench without an arm
     * model, -ERANGE the pose from the counts outside a joint's limits (+ the margin), -EPROTO
     * a count jumped further than the joint can move (a RESET, garbage), -ETIME the encoders
     * went unsampled too long to follow their wraps, else a transfer's -errno. hold_channel:
     * the channel (1-based) the check failed on, 0 none. */
    int64_t rest_ns;
    int32_t drop_urad;
    int32_t hold_phase;
    int32_t hold_status;
    int32_t hold_channel;
};

struct xrf_watch;

/* Start watching `pid` whose shared memory is `shm` (may be NULL: exit watching only, nothing to
 * force in memory). The mapping must outlive the watcher (stop it before unmapping). */
int xrf_watch_start(struct xrf_shm *shm, const struct xrf_watch_config *cfg,
                    struct xrf_watch **out);
/* The same with the bench's boards reached through `bench` instead of cfg->spi_device (which is
 * then ignored): a real bench's path without the hardware (tests give a simulated board, see
 * xrf_sim_follow). On success the watcher owns `bench` and closes it when freed; on failure it
 * stays the caller's. */
int xrf_watch_start_on(struct xrf_shm *shm, const struct xrf_watch_config *cfg,
                       struct xrf_ico_transport *bench, struct xrf_watch **out);
/* A real bench's `hold`: 0 while the watcher can hold the arm from the counts it follows, else
 * the hold_status a fault now would get (-EPROTO a count jumped, ...), hold_channel into
 * *channel (may be NULL). -ENOENT: not a real bench's hold. */
int xrf_watch_hold_ready(struct xrf_watch *w, int32_t *channel);

/* The host's event loop is alive at `now_ns` (CLOCK_MONOTONIC): the watcher beats the host
 * heartbeat on its behalf until now_ns + host_grace_ns (xrf_watch_config.host_beat_ns). One
 * atomic store: callable from any thread, never blocks. */
void xrf_watch_host_alive(struct xrf_watch *w, int64_t now_ns);
/* t->close(t) (xrf/ico.h), for a transport a failed xrf_watch_start_on left with the caller. */
void xrf_ico_close(struct xrf_ico_transport *t);
/* Every device of a bench's list (spi_device's format) opened and set up as the transports do,
 * then closed: 0, or the -errno of the first that failed and its index (0-based; -1 for the
 * list itself) in *failed (may be NULL). */
int xrf_spi_probe(const char *devices, uint32_t speed_hz, int32_t *failed);
/* A hang's diagnosis (XRF_DIAG_* records, read before the kill) into out (at most cap bytes,
 * whole records only): its length; 0 while watching or when the watcher did not declare a hang. */
uint32_t xrf_watch_diagnosis(struct xrf_watch *w, uint8_t *out, uint32_t cap);
/* Copy the result so far; returns its reason (XRF_WATCH_WATCHING while still watching). */
int xrf_watch_result(struct xrf_watch *w, struct xrf_watch_result *out);
/* End the watcher and free it. A loop that has already exited is still handled (outputs made
 * safe) before the thread ends, so the final result never misses an exit; a `hold` under way
 * is finished first (the arm at rest: at most the law's max_s, 20 s for the youBot). */
int xrf_watch_stop(struct xrf_watch *w, struct xrf_watch_result *out);
/* Wait until the watcher has finished (acted, and for `hold` the arm is at rest), then free it
 * like xrf_watch_stop; nothing is cancelled. */
int xrf_watch_wait(struct xrf_watch *w, struct xrf_watch_result *out);
/* Send the FPGA RESET frame once to every board of spidev `device` (a list as spi_device's;
 * also what the watcher does). */
int xrf_fpga_reset(const char *device, uint32_t speed_hz);
/* Send one ALL frame to board 1 with every PWM zero and only channel `brake_channel`'s (1..4)
 * digital output on, RESET to the other boards (what the watcher does for `brake`). 0 or
 * -errno (-EINVAL: no such channel). */
int xrf_fpga_brake(const char *device, uint32_t speed_hz, int brake_channel);
/* The name of safe reaction XRF_SAFE_REACTION_<NAME>, else NULL; the reaction a name spells,
 * else -EINVAL. */
const char *xrf_safe_reaction_name(int32_t reaction);
int32_t xrf_safe_reaction_parse(const char *name);
/* cffi-end */

/* The constants of XRF_SAFE_REACTIONS for C (cffi gets the same names from _cffi_build.py). */
#define XRF_SAFE_REACTION_CONST_(NAME, name, number) XRF_SAFE_REACTION_##NAME = number,
enum {
    XRF_SAFE_REACTIONS(XRF_SAFE_REACTION_CONST_) XRF_SAFE_REACTION_COUNT =
        0 XRF_SAFE_REACTIONS(XRF_COUNT_ONE_)
};

#ifdef __cplusplus
}
#endif

#endif /* XRF_WATCH_H */
