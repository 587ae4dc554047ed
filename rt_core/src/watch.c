/*
 * watch.c — the safety watcher (xrf/watch.h).
 *
 * One thread per watched run. It sleeps in poll() on two descriptors: the loop's pidfd (readable
 * once the process has exited, for any process, not only our children) and a cancel eventfd. The
 * poll timeout is the heartbeat check period. The thread allocates nothing after start and takes
 * no lock a host thread could hold, so a host stuck in Python cannot delay it.
 */
#define _GNU_SOURCE

#include "xrf/watch.h"

#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <pthread.h>
#include <sched.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/eventfd.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>

#include "plant.h"
#include "xrf/hold.h"
#include "xrf/ico.h"

#ifndef SYS_pidfd_open
#define SYS_pidfd_open 434
#endif
#ifndef SYS_pidfd_send_signal
#define SYS_pidfd_send_signal 424
#endif

struct xrf_watch {
    pthread_t thread;
    struct xrf_shm *shm;
    struct xrf_watch_config cfg;
    int pidfd;
    int cancel_fd;
    int host_fd; /* -1, or the host's pidfd (xrf_watch_config.host_pid) */
    /* Written by the watcher thread only, read by the host after `done` (acquire/release). */
    struct xrf_watch_result result;
    uint32_t done;
    /* hold on the simulated board: the plant's row and the watcher's own copy of the plant
     * (allocated at start: nothing is allocated once the loop is gone), the law's state. */
    const struct xrf_plant_ops *plant_ops;
    void *plant;
    struct xrf_hold hold;
    /* The closing sequence's progress, written by the watcher thread after `done` (atomics: the
     * host reads them meanwhile); copied into every result handed out. */
    int32_t drop_urad;
    int32_t hold_phase;
    int64_t rest_ns;

    /* The bench's boards, opened at start (spi_device) or given (xrf_watch_start_on): the safe
     * frames and a real bench's `hold` go there without opening anything once the loop is gone.
     * NULL: none (simulated bench), or the open failed (then tried again when needed). */
    struct xrf_ico_transport *bench;
    /* hold on a real bench: the arm (its plant row's model) and the counts followed since start.
     * Written by the watcher thread only; track_status/track_channel also read by the host
     * (atomics, xrf_watch_hold_ready). */
    const struct xrf_hold_arm *arm;
    double counts_per_rad[XRF_HOLD_JOINTS_MAX]; /* counts per joint radian, signed (inverted) */
    double pwm_sign[XRF_HOLD_JOINTS_MAX];       /* duty -> PWM word sign (direction, inverted) */
    int32_t enc_last[XRF_HOLD_JOINTS_MAX];      /* the last raw 14-bit count */
    int64_t enc_sum[XRF_HOLD_JOINTS_MAX];       /* counts since start, wraps followed */
    int64_t enc_t;                              /* when they were read */
    int32_t track_status;                       /* 0, or what hold_status will say */
    int32_t track_channel;
    int32_t track_gap_us; /* the failed check's sample gap (xrf_watch_result.hold_gap_us) */
    /* What the closing sequence ended with when it was given up or finished after `done`
     * (hold_status, hold_channel, reset_status), published by late_set: overlaid on results. */
    int32_t late_hold_status;
    int32_t late_hold_channel;
    int32_t late_reset_status;
    /* The host's event loop last said it was alive (xrf_watch_host_alive; atomics: the host
     * writes, the watcher thread reads), and when the watcher last beat for it. */
    int64_t host_alive_ns;
    int64_t host_beat_t;
    uint32_t late_set;
    int hang_is_exit; /* the late heartbeat's process was exiting (pid_exiting): told as an exit */
    /* A hang's diagnosis (xrf_watch_diagnosis): written by the watcher thread before `done`,
     * read by the host after it. Part of the allocation made at start: nothing allocated then. */
    uint32_t diag_len;
    uint8_t diag[XRF_WATCH_DIAG_BYTES];
};

static int64_t now_ns(void);

#define HOLD_TICK_NS 1000000LL /* the law at 1 kHz */
#define HOLD_SUBSTEP_S 100e-6  /* the plant in the board's own sub-steps */
#define HOLD_SEQ_TRIES 1000

static void hold_progress(struct xrf_watch *w, struct xrf_watch_result *out)
{
    out->drop_urad = __atomic_load_n(&w->drop_urad, __ATOMIC_RELAXED);
    out->hold_phase = __atomic_load_n(&w->hold_phase, __ATOMIC_RELAXED);
    out->rest_ns = __atomic_load_n(&w->rest_ns, __ATOMIC_ACQUIRE);
    out->hold_gap_us = __atomic_load_n(&w->track_gap_us, __ATOMIC_RELAXED);
    if (__atomic_load_n(&w->late_set, __ATOMIC_ACQUIRE)) {
        out->hold_status = w->late_hold_status;
        out->hold_channel = w->late_hold_channel;
        out->reset_status = w->late_reset_status;
    }
}

/* The closing sequence's end, told to the host however late (results overlay it). */
static void hold_end(struct xrf_watch *w, int32_t status, int32_t channel, int32_t reset)
{
    w->late_hold_status = status;
    w->late_hold_channel = channel;
    w->late_reset_status = reset;
    __atomic_store_n(&w->late_set, 1u, __ATOMIC_RELEASE);
}

static int64_t now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

/* One frame with board b (0-based) of a bench. */
static int xfer_on(struct xrf_ico_transport *t, int b, const uint8_t tx[XRF_ICO_FRAME],
                   uint8_t rx[XRF_ICO_FRAME])
{
    if (b == 0)
        return t->xfer(t, tx, rx);
    return t->xfer_board != NULL ? t->xfer_board(t, b, tx, rx) : -ENODEV;
}

static int bench_boards(const struct xrf_ico_transport *t)
{
    return t->boards >= 1 && t->boards <= XRF_MAX_BOARDS ? t->boards : 1;
}

/* The safe frame to every board of the bench: a RESET (outputs zero), or for `brake` (brake
 * channel 1..4, on board 1) an ALL frame with only the brake's output on there. The first
 * error is returned, but every board is tried: one board that does not answer must not leave
 * the others driving. */
static int bench_safe_frames(struct xrf_ico_transport *t, int brake_channel)
{
    int first = 0;
    for (int b = 0; b < bench_boards(t); b++) {
        uint8_t tx[XRF_ICO_FRAME], rx[XRF_ICO_FRAME];
        if (b == 0 && brake_channel >= 1 && brake_channel <= XRF_ICO_CHANNELS) {
            struct xrf_ico_out out = {{0}, {0}};
            out.dout[brake_channel - 1] = 1;
            xrf_ico_encode_all(&out, 0, tx);
        } else {
            xrf_ico_frame_op(XRF_ICO_RESET, tx);
        }
        int r = xfer_on(t, b, tx, rx);
        if (r < 0 && first == 0)
            first = r;
    }
    return first;
}

static int fpga_safe(const char *device, uint32_t speed_hz, int brake_channel)
{
    struct xrf_ico_transport *t = NULL;
    int r = xrf_spidev_open(device, speed_hz, &t);
    if (r < 0)
        return r;
    r = bench_safe_frames(t, brake_channel);
    t->close(t);
    return r;
}

int xrf_fpga_reset(const char *device, uint32_t speed_hz)
{
    return fpga_safe(device, speed_hz, 0);
}

int xrf_fpga_brake(const char *device, uint32_t speed_hz, int brake_channel)
{
    if (brake_channel < 1 || brake_channel > XRF_ICO_CHANNELS)
        return -EINVAL;
    return fpga_safe(device, speed_hz, brake_channel);
}

int xrf_spi_probe(const char *devices, uint32_t speed_hz, int32_t *failed)
{
    struct xrf_ico_transport *t = NULL;
    int bad = -1;
    int r = xrf_spidev_open_bench(devices, speed_hz, &t, &bad);
    if (failed != NULL)
        *failed = bad;
    if (r == 0)
        t->close(t);
    return r;
}

void xrf_ico_close(struct xrf_ico_transport *t)
{
    if (t != NULL && t->close != NULL)
        t->close(t);
}

#define XRF_SAFE_REACTION_CASE_(NAME, name, number) \
    case number:                                    \
        return name;
const char *xrf_safe_reaction_name(int32_t reaction)
{
    switch (reaction) {
        XRF_SAFE_REACTIONS(XRF_SAFE_REACTION_CASE_)
    default:
        return NULL;
    }
}

#define XRF_SAFE_REACTION_MATCH_(NAME, name, number) \
    if (strcmp(text, name) == 0)                     \
        return number;
int32_t xrf_safe_reaction_parse(const char *text)
{
    if (text == NULL)
        return -EINVAL;
    XRF_SAFE_REACTIONS(XRF_SAFE_REACTION_MATCH_)
    return -EINVAL;
}

/* The board's outputs as the safe reaction leaves them: over spidev, and the same on the
 * simulated board. */
static int send_safe_frame(const struct xrf_watch *w)
{
    int brake = w->cfg.safe_reaction == XRF_SAFE_REACTION_BRAKE ? w->cfg.brake_channel : 0;
    if (w->bench != NULL)
        return bench_safe_frames(w->bench, brake);
    /* The boards did not open at start: try once more now (this allocates, the one case). */
    return fpga_safe(w->cfg.spi_device, w->cfg.spi_speed_hz, brake);
}

/* --- hold on a real bench ----------------------------------------------------------------- */

#define ENC_HALF (XRF_ICO_ENC_MODULO / 2)

/* gap_s: the time between the samples a failed count check compared, < 0 for other failures. */
static void track_fail(struct xrf_watch *w, int status, int joint, double gap_s)
{
    if (__atomic_load_n(&w->track_status, __ATOMIC_RELAXED) != 0)
        return; /* the first reason is the one that matters */
    if (gap_s >= 0.0)
        __atomic_store_n(&w->track_gap_us, gap_s < 2000.0 ? (int32_t)lrint(gap_s * 1e6) : INT32_MAX,
                         __ATOMIC_RELAXED);
    __atomic_store_n(&w->track_channel, w->arm->joint[joint].channel + 1, __ATOMIC_RELAXED);
    __atomic_store_n(&w->track_status, status, __ATOMIC_RELEASE);
}

/* New raw counts of every joint, read at t: each wrap of the 14-bit counter followed. The
 * motion since the last count is the one candidate (the difference, +- a wrap) within what the
 * joint can move in the time between (max_speed). None: the count is no motion of the arm (a
 * RESET someone sent, garbage on the wire), -EPROTO; more than one: the samples were too far
 * apart to tell a wrap from a motion, -ETIME. Either way the pose is unknown from then on. */
static int track(struct xrf_watch *w, const int32_t *counts, int64_t t)
{
    const struct xrf_hold_arm *arm = w->arm;
    double dt = (double)(t - w->enc_t) * 1e-9;
    if (dt < 0.0)
        dt = 0.0;
    for (int i = 0; i < arm->joints; i++) {
        int32_t d = (counts[i] - w->enc_last[i]) & (XRF_ICO_ENC_MODULO - 1);
        if (d >= ENC_HALF)
            d -= XRF_ICO_ENC_MODULO;
        /* +4 counts: quantisation and the counter's own edge jitter at standstill. */
        double bound = arm->max_speed * fabs(w->counts_per_rad[i]) * dt + 4.0;
        if (fabs((double)d) > bound) {
            track_fail(w, -EPROTO, i, dt);
            return -EPROTO;
        }
        if (XRF_ICO_ENC_MODULO - fabs((double)d) <= bound) {
            track_fail(w, -ETIME, i, dt);
            return -ETIME;
        }
        w->enc_sum[i] += d;
        w->enc_last[i] = counts[i];
    }
    w->enc_t = t;
    return 0;
}

/* Every joint's raw count with read-only frames (ENC_n): nothing the loop set is changed. */
static int read_counts(struct xrf_watch *w, int32_t *counts)
{
    const struct xrf_hold_arm *arm = w->arm;
    for (int i = 0; i < arm->joints; i++) {
        int ch = arm->joint[i].channel;
        uint8_t tx[XRF_ICO_FRAME], rx[XRF_ICO_FRAME];
        xrf_ico_frame_op((uint8_t)(XRF_ICO_ENC_1 + ch % XRF_ICO_CHANNELS), tx);
        int r = xfer_on(w->bench, ch / XRF_ICO_CHANNELS, tx, rx);
        if (r < 0)
            return r;
        counts[i] = xrf_ico_decode_enc(rx) & (XRF_ICO_ENC_MODULO - 1);
    }
    return 0;
}

/* The pose from the counts followed since start: zero pose + counts / scale, believed only
 * inside each joint's limits plus XRF_WATCH_POSE_MARGIN_DEG (-ERANGE otherwise). */
static int board_pose(struct xrf_watch *w, double *q)
{
    const struct xrf_hold_arm *arm = w->arm;
    const double margin = XRF_WATCH_POSE_MARGIN_DEG * (M_PI / 180.0);
    for (int i = 0; i < arm->joints; i++) {
        const struct xrf_hold_joint *j = &arm->joint[i];
        q[i] = j->zero + (double)w->enc_sum[i] / w->counts_per_rad[i];
        if (!isfinite(q[i]) || q[i] < j->lo - margin || q[i] > j->hi + margin) {
            track_fail(w, -ERANGE, i, -1.0);
            return -ERANGE;
        }
    }
    return 0;
}

/* One sample while watching (or the first, at start: the reference). */
static void board_sample(struct xrf_watch *w, int first)
{
    if (__atomic_load_n(&w->track_status, __ATOMIC_RELAXED) != 0)
        return;
    int32_t counts[XRF_HOLD_JOINTS_MAX];
    int64_t t = now_ns();
    int r = read_counts(w, counts);
    if (r < 0) {
        track_fail(w, r, 0, -1.0);
        return;
    }
    if (first) {
        for (int i = 0; i < w->arm->joints; i++) {
            w->enc_last[i] = counts[i];
            w->enc_sum[i] = 0;
        }
        w->enc_t = t;
        return;
    }
    /* The pose is checked while watching too: a wrong reference is known (and the host told,
     * xrf_watch_hold_ready) before a fault needs it. */
    double q[XRF_HOLD_JOINTS_MAX];
    if (track(w, counts, t) == 0)
        board_pose(w, q);
}

/* The law's duties out as one ALL frame per board (channels the arm does not drive: zero, the
 * wheels stop), each reply's counts (latched before the new outputs) into counts. */
static int board_out(struct xrf_watch *w, const double *duty, int32_t *counts)
{
    const struct xrf_hold_arm *arm = w->arm;
    for (int b = 0; b < bench_boards(w->bench); b++) {
        struct xrf_ico_out out = {{0}, {0}};
        for (int i = 0; i < arm->joints; i++) {
            int ch = arm->joint[i].channel;
            if (ch / XRF_ICO_CHANNELS == b)
                out.pwm[ch % XRF_ICO_CHANNELS] =
                    (int16_t)lrint(duty[ch] * w->pwm_sign[i] * XRF_ICO_PWM_FULL);
        }
        uint8_t tx[XRF_ICO_FRAME], rx[XRF_ICO_FRAME];
        xrf_ico_encode_all(&out, XRF_ICO_PWM_FULL, tx);
        int r = xfer_on(w->bench, b, tx, rx);
        if (r < 0)
            return r;
        struct xrf_ico_in in;
        xrf_ico_decode_all(rx, &in);
        for (int i = 0; i < arm->joints; i++) {
            int ch = arm->joint[i].channel;
            if (ch / XRF_ICO_CHANNELS == b)
                counts[i] = in.enc[ch % XRF_ICO_CHANNELS];
        }
    }
    return 0;
}

/* Give up holding: every board's outputs safe (RESET), the reason kept. */
static void board_give_up(struct xrf_watch *w, int status)
{
    track_fail(w, status, 0, -1.0);
    int reset = send_safe_frame(w);
    hold_end(w, __atomic_load_n(&w->track_status, __ATOMIC_RELAXED),
             __atomic_load_n(&w->track_channel, __ATOMIC_RELAXED), reset);
}

/* The first hold output on a real bench: the last counts read, the pose checked, the law's
 * first duties out. 1 holding; 0 the pose is not believed (outputs zeroed, hold_status why). */
static int board_hold_begin(struct xrf_watch *w, double *duty)
{
    board_sample(w, 0);
    double q[XRF_HOLD_JOINTS_MAX];
    int r = __atomic_load_n(&w->track_status, __ATOMIC_RELAXED);
    if (r == 0)
        r = board_pose(w, q);
    if (r != 0) {
        board_give_up(w, r);
        return 0;
    }
    xrf_hold_begin(&w->hold, w->arm, q);
    __atomic_store_n(&w->hold_phase, xrf_hold_step(&w->hold, q, HOLD_TICK_NS * 1e-9, duty),
                     __ATOMIC_RELAXED);
    int32_t counts[XRF_HOLD_JOINTS_MAX];
    r = board_out(w, duty, counts);
    if (r == 0)
        r = track(w, counts, now_ns());
    if (r != 0) {
        board_give_up(w, r);
        return 0;
    }
    return 1;
}

/* --- hold on the simulated board ---------------------------------------------------------- */

static void hold_angles(const struct xrf_watch *w, double *q)
{
    const struct xrf_hold_arm *arm = w->plant_ops->arm;
    for (int i = 0; i < arm->joints; i++) {
        const struct xrf_hold_joint *j = &arm->joint[i];
        q[i] = w->plant_ops->motor_angle(w->plant, j->channel) / j->gear;
    }
}

/* The board's last snapshot into the watcher's plant: a consistent copy if the seqlock gives one
 * within a bounded number of tries (a loop killed mid-write leaves it odd for ever), else the
 * values as they are. Only the plant's own count of values is read, and `load` sanitises them. */
static void hold_take_plant(struct xrf_watch *w)
{
    const struct xrf_sim_snapshot *sn = &w->shm->sim_snapshot;
    double v[XRF_SIM_SNAPSHOT_MAX];
    int n = w->plant_ops->snapshot_len;
    for (int tries = 0; tries < HOLD_SEQ_TRIES; tries++) {
        uint32_t a = __atomic_load_n(&sn->seq, __ATOMIC_ACQUIRE);
        memcpy(v, (const void *)sn->v, (size_t)n * sizeof v[0]);
        __atomic_thread_fence(__ATOMIC_ACQUIRE);
        if ((a & 1u) == 0 && __atomic_load_n(&sn->seq, __ATOMIC_RELAXED) == a)
            break;
    }
    w->plant_ops->init(w->plant);
    w->plant_ops->load(w->plant, v, n);
}

/* What viewers and tests see of the plant the watcher now steps (the board's mirror). */
static void hold_mirror(struct xrf_watch *w, const double *duty)
{
    struct xrf_sim_outputs *o = &w->shm->sim;
    for (int ch = 0; ch < XRF_MAX_CHANNELS; ch++)
        __atomic_store_n(&o->pwm[ch], (int16_t)lrint(duty[ch] * XRF_ICO_PWM_FULL),
                         __ATOMIC_RELAXED);
    double st[8];
    int n = w->plant_ops->state(w->plant, st, 8);
    for (int i = 0; i < n; i++)
        o->plant[i] = st[i];
}

/* The first hold output: the law started at the measured pose; the plant does not move between
 * the loop's last transfer and this (nothing steps it). */
static void hold_begin(struct xrf_watch *w, double *duty)
{
    double q[XRF_HOLD_JOINTS_MAX];
    hold_take_plant(w);
    hold_angles(w, q);
    xrf_hold_begin(&w->hold, w->plant_ops->arm, q);
    __atomic_store_n(&w->hold_phase, xrf_hold_step(&w->hold, q, HOLD_TICK_NS * 1e-9, duty),
                     __ATOMIC_RELAXED);
    hold_mirror(w, duty);
}

/* The closing sequence to its end: the plant stepped in real time by the duty the law gives
 * each tick, until the law says REST (outputs zero, the arm on its stops). */
static void hold_run(struct xrf_watch *w, double *duty)
{
    struct timespec next;
    clock_gettime(CLOCK_MONOTONIC, &next);
    int64_t last = now_ns();
    while (__atomic_load_n(&w->hold_phase, __ATOMIC_RELAXED) != XRF_HOLD_PHASE_REST) {
        next.tv_nsec += HOLD_TICK_NS;
        if (next.tv_nsec >= 1000000000L) {
            next.tv_nsec -= 1000000000L;
            next.tv_sec++;
        }
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, NULL);
        int64_t t = now_ns();
        double dt = (double)(t - last) * 1e-9;
        last = t;
        if (dt > 0.05)
            dt = 0.05; /* as the board: a stalled watcher must not make the plant jump */
        int steps = (int)ceil(dt / HOLD_SUBSTEP_S);
        for (int i = 0; i < steps; i++)
            w->plant_ops->step(w->plant, duty, dt / steps);
        double q[XRF_HOLD_JOINTS_MAX];
        hold_angles(w, q);
        int phase = xrf_hold_step(&w->hold, q, dt, duty);
        __atomic_store_n(&w->drop_urad, (int32_t)lrint(w->hold.drop_max * 1e6), __ATOMIC_RELAXED);
        __atomic_store_n(&w->hold_phase, phase, __ATOMIC_RELAXED);
        hold_mirror(w, duty);
    }
    __atomic_store_n(&w->rest_ns, now_ns(), __ATOMIC_RELEASE);
}

static void next_tick(struct timespec *next)
{
    next->tv_nsec += HOLD_TICK_NS;
    if (next->tv_nsec >= 1000000000L) {
        next->tv_nsec -= 1000000000L;
        next->tv_sec++;
    }
    clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, next, NULL);
}

/* The closing sequence on a real bench, at 1 kHz: each tick one ALL frame per board carries the
 * duties and brings the counts back; the counts are followed and checked as while watching (a
 * RESET or garbage now ends the hold with zero outputs: a pose not believed is not held). At
 * REST every board gets its safe frame. */
static void board_hold_run(struct xrf_watch *w, double *duty)
{
    struct timespec next;
    clock_gettime(CLOCK_MONOTONIC, &next);
    int64_t last = now_ns();
    while (__atomic_load_n(&w->hold_phase, __ATOMIC_RELAXED) != XRF_HOLD_PHASE_REST) {
        next_tick(&next);
        int64_t t = now_ns();
        double dt = (double)(t - last) * 1e-9;
        last = t;
        int32_t counts[XRF_HOLD_JOINTS_MAX];
        double q[XRF_HOLD_JOINTS_MAX];
        int r = board_out(w, duty, counts);
        if (r == 0)
            r = track(w, counts, t);
        if (r == 0)
            r = board_pose(w, q);
        if (r != 0) {
            board_give_up(w, r);
            return;
        }
        int phase = xrf_hold_step(&w->hold, q, dt, duty);
        __atomic_store_n(&w->drop_urad, (int32_t)lrint(w->hold.drop_max * 1e6), __ATOMIC_RELAXED);
        __atomic_store_n(&w->hold_phase, phase, __ATOMIC_RELAXED);
    }
    hold_end(w, 0, 0, send_safe_frame(w));
    __atomic_store_n(&w->rest_ns, now_ns(), __ATOMIC_RELEASE);
}

/* Outputs safe: the simulated board's outputs zeroed (but the brake's) and ignored from now on,
 * the FPGA's likewise. */
static void make_safe(struct xrf_watch *w)
{
    int brake = w->cfg.safe_reaction == XRF_SAFE_REACTION_BRAKE ? w->cfg.brake_channel - 1 : -1;
    if (w->cfg.force_sim && w->shm != NULL) {
        struct xrf_sim_outputs *o = &w->shm->sim;
        /* What the pins show once forced, written before forced_off is published. */
        for (int i = 0; i < XRF_MAX_CHANNELS; i++) /* every channel any bench can have */
            __atomic_store_n(&o->forced_dout[i], (uint8_t)(i == brake), __ATOMIC_RELAXED);
        __atomic_store_n(&o->forced_off, 1u, __ATOMIC_RELEASE);
        for (int i = 0; i < XRF_MAX_CHANNELS; i++) {
            __atomic_store_n(&o->pwm[i], (int16_t)0, __ATOMIC_RELAXED);
            __atomic_store_n(&o->dout[i], (uint8_t)(i == brake), __ATOMIC_RELAXED);
        }
        w->result.sim_forced = 1;
    }
    if (w->bench != NULL || w->cfg.spi_device[0] != '\0')
        w->result.reset_status = send_safe_frame(w);
}

static void finish(struct xrf_watch *w, int reason, int64_t event_ns)
{
    double duty[XRF_MAX_CHANNELS] = {0};
    int holding = 0;
    if (w->shm != NULL) /* the last cycle's start: the loop ended (or hung) after it */
        w->result.heartbeat_ns = __atomic_load_n(&w->shm->status.heartbeat_ns, __ATOMIC_RELAXED);
    /* A hang of a process already exiting is told as its exit; it is handled as a hang all the
     * same (killed, reset again once gone): a thread of it may still be driving the outputs. */
    w->result.reason = reason == XRF_WATCH_HANG && w->hang_is_exit ? XRF_WATCH_EXIT : reason;
    w->result.event_ns = event_ns;
    if (reason == XRF_WATCH_HANG || reason == XRF_WATCH_HOST_GONE) {
        /* Stop it from driving the outputs again before resetting them: a SIGKILLed process
         * runs no more user code. Through the pidfd, so a recycled pid cannot be hit. */
        w->result.kill_status =
            syscall(SYS_pidfd_send_signal, w->pidfd, SIGKILL, NULL, 0) == 0 ? 0 : -errno;
    }
    int board_holding = 0;
    if (reason == XRF_WATCH_EXIT || reason == XRF_WATCH_HANG || reason == XRF_WATCH_HOST_GONE) {
        if (w->arm != NULL) {
            /* A real bench's arm: driven by the watcher's frames from here, never RESET first
             * (that would drop it); a pose it cannot believe gets the RESET instead. */
            board_holding = board_hold_begin(w, duty);
        } else {
            make_safe(w); /* the board's own outputs off: from here the watcher drives the plant */
            holding = w->plant != NULL && w->shm != NULL && w->cfg.force_sim;
            if (holding)
                hold_begin(w, duty);
        }
        w->result.safe_ns = now_ns();
    }
    if ((reason == XRF_WATCH_HANG || reason == XRF_WATCH_HOST_GONE) && !board_holding &&
        (w->bench != NULL || w->cfg.spi_device[0] != '\0')) {
        /* A transfer the killed loop had in flight may complete after our RESET: once the
         * process is really gone (at most 100 ms), reset again. */
        struct pollfd p = {.fd = w->pidfd, .events = POLLIN};
        if (poll(&p, 1, 100) == 1)
            w->result.reset_status = send_safe_frame(w);
    }
    __atomic_store_n(&w->done, 1u, __ATOMIC_RELEASE);
    if (w->cfg.notify_fd >= 0) {
        uint64_t one = 1;
        ssize_t n = write(w->cfg.notify_fd, &one, sizeof one);
        (void)n; /* an eventfd write of 1 only fails at 2^64-1 pending: cannot happen here */
    }
    /* The host is told once the first hold output is out; the closing sequence goes on here,
     * whatever the host does (xrf_watch_stop waits for it). */
    if (holding)
        hold_run(w, duty);
    if (board_holding)
        board_hold_run(w, duty);
}

/* Keep the watcher off the run's CPUs: a controller's spinning SCHED_FIFO threads there
 * cannot delay it, whatever their priority. Only where another CPU is left to it. */
static void avoid_cpus(uint64_t avoid)
{
    if (avoid == 0)
        return;
    cpu_set_t set;
    CPU_ZERO(&set);
    if (sched_getaffinity(0, sizeof set, &set) != 0)
        return;
    for (int c = 0; c < 64; c++)
        if (avoid & (UINT64_C(1) << c))
            CPU_CLR(c, &set);
    if (CPU_COUNT(&set) > 0)
        (void)sched_setaffinity(0, sizeof set, &set);
}

/* PF_EXITING (the kernel's linux/sched.h): the task is in do_exit. */
#define XRF_PF_EXITING 0x00000004UL

/* Whether process `pid` is on its way out. Its pidfd turns readable only once the exit is done,
 * after its memory is torn down; a loop that crashed or exited with a large locked mapping on a
 * loaded machine can take longer than the hang timeout to get there (CI: a segfault reported as a
 * hang): a late heartbeat is then an exit, not a hang. The flags of /proc/PID/stat (field 9),
 * read into a stack buffer when a hang is due: no allocation, and never on the loop's side. */
static int pid_exiting(pid_t pid)
{
    char path[40], buf[512];
    snprintf(path, sizeof path, "/proc/%d/stat", (int)pid);
    int fd = open(path, O_RDONLY | O_CLOEXEC);
    if (fd < 0)
        return errno == ENOENT; /* reaped meanwhile: it exited */
    ssize_t n = read(fd, buf, sizeof buf - 1);
    close(fd);
    if (n <= 0)
        return 0;
    buf[n] = '\0';
    const char *p = strrchr(buf, ')'); /* the name may hold spaces and parentheses */
    unsigned long flags = 0;
    /* After the name: state ppid pgrp session tty_nr tpgid flags. */
    if (p == NULL || sscanf(p + 1, " %*c %*d %*d %*d %*d %*d %lu", &flags) != 1)
        return 0;
    return (flags & XRF_PF_EXITING) != 0;
}

/* --- a hang's diagnosis ------------------------------------------------------------------- */

/* One record: a header and up to `max` bytes of the file at `path` (opened, read once, closed),
 * appended to the diagnosis if it fits. Files a process's threads expose that take no lock the
 * loop could hold (no mmap_lock: never maps, smaps, cmdline or environ), each read bounded:
 * a watcher stuck here could not make the outputs safe. */
static void diag_file(struct xrf_watch *w, int kind, int tid, const char *path, uint32_t max)
{
    struct xrf_watch_diag_rec rec = {.kind = (uint16_t)kind, .len = 0, .tid = tid};
    if (w->diag_len + sizeof rec + 1 > sizeof w->diag)
        return;
    uint32_t room = (uint32_t)(sizeof w->diag - w->diag_len - sizeof rec);
    if (max > room)
        max = room;
    if (max > UINT16_MAX)
        max = UINT16_MAX;
    int fd = open(path, O_RDONLY | O_CLOEXEC | O_NONBLOCK);
    if (fd < 0)
        return; /* gone, or not ours to read (stack, wchan as another user): left out */
    uint8_t *data = w->diag + w->diag_len + sizeof rec;
    uint32_t got = 0;
    while (got < max) {
        ssize_t n = read(fd, data + got, max - got);
        if (n <= 0)
            break;
        got += (uint32_t)n;
    }
    close(fd);
    rec.len = (uint16_t)got;
    memcpy(w->diag + w->diag_len, &rec, sizeof rec);
    w->diag_len += (uint32_t)(sizeof rec + got);
}

static void diag_text(struct xrf_watch *w, int kind, const char *text)
{
    struct xrf_watch_diag_rec rec = {.kind = (uint16_t)kind, .len = 0, .tid = 0};
    size_t n = strlen(text);
    if (w->diag_len + sizeof rec + n > sizeof w->diag)
        return;
    rec.len = (uint16_t)n;
    memcpy(w->diag + w->diag_len, &rec, sizeof rec);
    memcpy(w->diag + w->diag_len + sizeof rec, text, n);
    w->diag_len += (uint32_t)(sizeof rec + n);
}

struct diag_dirent {
    uint64_t ino;
    int64_t off;
    unsigned short reclen;
    unsigned char type;
    char name[];
};

/* A numeric directory entry's value, or 0. */
static int diag_number(const char *name)
{
    char *end = NULL;
    long v = strtol(name, &end, 10);
    return end != name && *end == '\0' && v > 0 && v < INT32_MAX ? (int)v : 0;
}

/* The loop process's thread ids (at most XRF_WATCH_DIAG_TASKS): getdents64 into a stack buffer
 * (opendir would allocate). */
static int diag_tasks(pid_t pid, int *tids)
{
    char path[48];
    snprintf(path, sizeof path, "/proc/%d/task", (int)pid);
    int fd = open(path, O_RDONLY | O_DIRECTORY | O_CLOEXEC);
    if (fd < 0)
        return 0;
    int count = 0;
    char buf[2048] __attribute__((aligned(8)));
    for (;;) {
        long n = syscall(SYS_getdents64, fd, buf, sizeof buf);
        if (n <= 0)
            break;
        for (long off = 0; off < n;) {
            const struct diag_dirent *d = (const struct diag_dirent *)(buf + off);
            if (d->reclen == 0)
                break;
            off += d->reclen;
            const int tid = diag_number(d->name);
            if (tid > 0 && count < XRF_WATCH_DIAG_TASKS)
                tids[count++] = tid;
        }
        if (count >= XRF_WATCH_DIAG_TASKS)
            break;
    }
    close(fd);
    return count;
}

/* stat text's state and scheduling policy (fields 3 and 41): after the last ')', the name may
 * hold anything. 0 when the text is not a stat line. */
static int diag_stat_fields(const char *buf, char *state, long *policy)
{
    const char *p = strrchr(buf, ')');
    if (p == NULL || p[1] != ' ' || p[2] == '\0')
        return 0;
    *state = p[2];
    p += 3;
    for (int field = 4; field <= 41; field++) { /* on to the start of field 41 */
        p = strchr(p, ' ');
        if (p == NULL)
            return 0;
        p++;
    }
    *policy = strtol(p, NULL, 10);
    return 1;
}

/* Every other process's runnable real-time tasks (state R, SCHED_FIFO/RR/DEADLINE): what can keep
 * a SCHED_FIFO loop off its CPU. Bounded: at most XRF_WATCH_DIAG_SCAN tasks read, 10 ms. */
static int diag_others(struct xrf_watch *w, pid_t self_pid, int *found_pids, int *found_tids)
{
    const int watcher_tid = (int)syscall(SYS_gettid);
    const int64_t until = now_ns() + 10000000;
    int procfd = open("/proc", O_RDONLY | O_DIRECTORY | O_CLOEXEC);
    if (procfd < 0)
        return 0;
    char buf[2048] __attribute__((aligned(8)));
    int scanned = 0, found = 0;
    for (;;) {
        long n = syscall(SYS_getdents64, procfd, buf, sizeof buf);
        if (n <= 0)
            break;
        for (long off = 0;
             off < n && scanned < XRF_WATCH_DIAG_SCAN && found < XRF_WATCH_DIAG_OTHERS;) {
            const struct diag_dirent *d = (const struct diag_dirent *)(buf + off);
            if (d->reclen == 0)
                break;
            off += d->reclen;
            const int pid = diag_number(d->name);
            if (pid == 0 || pid == self_pid)
                continue;
            if (now_ns() > until)
                break; /* the time bound, per process: a machine with thousands of threads */
            int tids[XRF_WATCH_DIAG_TASKS];
            const int count = diag_tasks(pid, tids);
            for (int i = 0; i < count && found < XRF_WATCH_DIAG_OTHERS; i++) {
                char path[64], stat[600];
                if (tids[i] == watcher_tid)
                    continue; /* this thread: real-time and running, of course */
                snprintf(path, sizeof path, "/proc/%d/task/%d/stat", pid, tids[i]);
                int fd = open(path, O_RDONLY | O_CLOEXEC | O_NONBLOCK);
                if (fd < 0)
                    continue;
                ssize_t len = read(fd, stat, sizeof stat - 1);
                close(fd);
                scanned++;
                if (len <= 0)
                    continue;
                stat[len] = '\0';
                char state = 0;
                long policy = 0;
                if (diag_stat_fields(stat, &state, &policy) && state == 'R' &&
                    (policy == SCHED_FIFO || policy == SCHED_RR || policy == 6 /* DEADLINE */)) {
                    diag_file(w, XRF_DIAG_OTHER, tids[i], path, sizeof stat);
                    snprintf(path, sizeof path, "/proc/%d/task/%d/schedstat", pid, tids[i]);
                    diag_file(w, XRF_DIAG_OTHER_SCHEDSTAT, tids[i], path, 96);
                    found_pids[found] = pid;
                    found_tids[found] = tids[i];
                    found++;
                }
            }
        }
        if (scanned >= XRF_WATCH_DIAG_SCAN || found >= XRF_WATCH_DIAG_OTHERS || now_ns() > until)
            break;
    }
    close(procfd);
    return found;
}

/* Where the loop process's threads are at the hang, before the kill: each thread's state and
 * kernel wait channel, system call, scheduling and context switches (stat, status), its CPU time
 * and run-queue wait twice 10 ms apart (on a CPU, waiting for one, or asleep), its kernel stack
 * where readable (root); and the other programs' runnable real-time threads, likewise (who held
 * the CPU). Small reads and a 10 ms wait, ~15 ms in all, only at a hang, before the kill; the
 * host turns them into words (server/runs/hang_diag.py) and treats every byte as the guest's (its
 * threads name themselves). */
static void diagnose(struct xrf_watch *w, int64_t heartbeat)
{
    static const struct {
        int kind;
        const char *file;
        uint32_t max;
    } files[] = {
        {XRF_DIAG_STAT, "stat", 600},          {XRF_DIAG_STATUS, "status", 1800},
        {XRF_DIAG_WCHAN, "wchan", 96},         {XRF_DIAG_SYSCALL, "syscall", 200},
        {XRF_DIAG_SCHEDSTAT, "schedstat", 96}, {XRF_DIAG_STACK, "stack", 1200},
    };
    const pid_t pid = w->cfg.pid;
    int tids[XRF_WATCH_DIAG_TASKS];
    char path[96];
    w->diag_len = 0;
    const int64_t t0 = now_ns();
    const int n = diag_tasks(pid, tids);
    snprintf(path, sizeof path, "/proc/%d/cgroup", (int)pid);
    diag_file(w, XRF_DIAG_CGROUP, 0, path, 1024);
    for (int i = 0; i < n; i++) {
        for (size_t f = 0; f < sizeof files / sizeof files[0]; f++) {
            snprintf(path, sizeof path, "/proc/%d/task/%d/%s", (int)pid, tids[i], files[f].file);
            diag_file(w, files[f].kind, tids[i], path, files[f].max);
        }
    }
    int other_pids[XRF_WATCH_DIAG_OTHERS], other_tids[XRF_WATCH_DIAG_OTHERS];
    const int others = diag_others(w, pid, other_pids, other_tids);
    /* The second look at the CPU-time counters, 10 ms after the first: they move at the
     * scheduler's tick (4 ms at 250 Hz) while a task runs, not at all while it waits or sleeps. */
    struct timespec until;
    int64_t t_until = t0 + 10000000;
    until.tv_sec = (time_t)(t_until / 1000000000LL);
    until.tv_nsec = (long)(t_until % 1000000000LL);
    clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &until, NULL);
    const int64_t t1 = now_ns();
    for (int i = 0; i < n; i++) {
        snprintf(path, sizeof path, "/proc/%d/task/%d/schedstat", (int)pid, tids[i]);
        diag_file(w, XRF_DIAG_SCHEDSTAT2, tids[i], path, 96);
    }
    for (int i = 0; i < others; i++) {
        snprintf(path, sizeof path, "/proc/%d/task/%d/schedstat", other_pids[i], other_tids[i]);
        diag_file(w, XRF_DIAG_OTHER_SCHEDSTAT2, other_tids[i], path, 96);
    }
    char meta[128];
    snprintf(meta, sizeof meta, "%lld %lld %lld %lld", (long long)t0, (long long)t1,
             (long long)now_ns(), (long long)heartbeat);
    diag_text(w, XRF_DIAG_META, meta);
}

static void *watch_thread(void *arg)
{
    struct xrf_watch *w = arg;
    avoid_cpus(w->cfg.avoid_cpus);
    if (w->cfg.rt_priority > 0) {
        struct sched_param sp = {.sched_priority = w->cfg.rt_priority};
        w->result.rt_status = -pthread_setschedparam(pthread_self(), SCHED_FIFO, &sp);
    }
    int timeout_ms = (int)(w->cfg.check_ns / 1000000);
    if (timeout_ms < 1)
        timeout_ms = 1;
    /* A real bench's arm: its counters are followed between the checks too (their wraps). */
    if (w->arm != NULL && timeout_ms > XRF_WATCH_SAMPLE_NS / 1000000)
        timeout_ms = XRF_WATCH_SAMPLE_NS / 1000000;
    const struct xrf_status *st = w->shm ? &w->shm->status : NULL;
    const int hang_checked = st != NULL && w->cfg.hang_timeout_ns > 0 && !w->cfg.host_only;
    /* The host heartbeat on the event loop's behalf (xrf_watch_config.host_beat_ns): a word
     * the loop only reads, one relaxed store, as the host's own beat is. */
    const int beats = st != NULL && w->cfg.host_beat_ns > 0 && !w->cfg.host_only;
    for (;;) {
        struct pollfd fds[3] = {{.fd = w->pidfd, .events = POLLIN},
                                {.fd = w->cancel_fd, .events = POLLIN},
                                {.fd = w->host_fd, .events = POLLIN}};
        /* A running loop's hang cannot be due before its last heartbeat plus the timeout: sleep
         * until then (+1 ms, poll's rounding), not a check period at a time. The same detection
         * time, with ~5 wake-ups a second instead of 50 for a 200 ms timeout: an idle appliance
         * pays for each. A real bench's arm keeps its 2 ms count samples (the wraps). */
        int wait_ms = timeout_ms;
        if (hang_checked && w->arm == NULL && __atomic_load_n(&st->running, __ATOMIC_RELAXED)) {
            int64_t hb = __atomic_load_n(&st->heartbeat_ns, __ATOMIC_RELAXED);
            int64_t left = hb + w->cfg.hang_timeout_ns - now_ns();
            if (hb > 0 && left > (int64_t)timeout_ms * 1000000)
                wait_ms = left > w->cfg.hang_timeout_ns
                              ? (int)(w->cfg.hang_timeout_ns / 1000000) + 1
                              : (int)(left / 1000000) + 1;
        }
        if (beats && st != NULL) {
            int64_t left = w->host_beat_t + w->cfg.host_beat_ns - now_ns();
            int beat_ms = left > 0 ? (int)(left / 1000000) + 1 : 0;
            if (beat_ms < wait_ms)
                wait_ms = beat_ms;
        }
        int n = poll(fds, w->host_fd >= 0 ? 3 : 2, wait_ms);
        int64_t t = now_ns();
        /* The exit comes first: a cancel that races with it still gets the outputs made safe. */
        if (n > 0 && (fds[0].revents & (POLLIN | POLLHUP | POLLERR))) {
            finish(w, w->cfg.host_only ? XRF_WATCH_LOOP_ENDED : XRF_WATCH_EXIT, t);
            return NULL;
        }
        if (n > 0 && w->host_fd >= 0 && (fds[2].revents & (POLLIN | POLLHUP | POLLERR))) {
            finish(w, XRF_WATCH_HOST_GONE, t);
            return NULL;
        }
        if (n > 0 && (fds[1].revents & POLLIN)) {
            finish(w, XRF_WATCH_CANCELLED, t);
            return NULL;
        }
        if (w->arm != NULL)
            board_sample(w, 0);
        if (beats && t - w->host_beat_t >= w->cfg.host_beat_ns) {
            w->host_beat_t = t;
            int64_t alive = __atomic_load_n(&w->host_alive_ns, __ATOMIC_RELAXED);
            if (t - alive < w->cfg.host_grace_ns)
                __atomic_store_n(&w->shm->host_heartbeat_ns, t, __ATOMIC_RELAXED);
        }
        if (hang_checked) {
            /* Single aligned words, read without the seqlock: a loop stopped mid-write must
             * not look alive (the seqlock would make it unreadable, never stale). */
            int32_t running = __atomic_load_n(&st->running, __ATOMIC_RELAXED);
            int64_t hb = __atomic_load_n(&st->heartbeat_ns, __ATOMIC_RELAXED);
            w->result.heartbeat_ns = hb;
            if (running && hb > 0 && t - hb > w->cfg.hang_timeout_ns) {
                w->hang_is_exit = pid_exiting(w->cfg.pid);
                if (!w->hang_is_exit)
                    diagnose(w, hb);
                finish(w, XRF_WATCH_HANG, t);
                return NULL;
            }
        }
    }
}

/* hold on a real bench: the arm and the counts' scale, the reference counts read now (the
 * bench guarantees the arm parked at its zero pose when the run starts). */
static int board_hold_setup(struct xrf_watch *w, const struct xrf_plant_ops *ops)
{
    const struct xrf_hold_arm *arm = ops->arm;
    const struct xrf_watch_config *cfg = &w->cfg;
    if (cfg->enc_counts_per_rev <= 0 || !(arm->max_speed > 0.0))
        return -EINVAL;
    for (int i = 0; i < arm->joints; i++) {
        const struct xrf_hold_joint *j = &arm->joint[i];
        if (j->channel < 0 || j->channel >= XRF_ICO_CHANNELS * bench_boards(w->bench))
            return -EINVAL; /* a joint on a board the bench does not reach */
        uint32_t bit = 1u << j->channel;
        double enc = (cfg->enc_inverted & bit) ? -1.0 : 1.0;
        double pwm = (cfg->pwm_reversed & bit) ? -1.0 : 1.0;
        w->counts_per_rad[i] = enc * cfg->enc_counts_per_rev * j->gear / (2.0 * M_PI);
        /* A positive duty turns the joint positive: its counts go the way `direction` says,
         * and the joint the way the encoder's sign says of those counts. */
        w->pwm_sign[i] = pwm * enc;
    }
    w->arm = arm;
    board_sample(w, 1);
    return 0;
}

static void watch_free(struct xrf_watch *w)
{
    if (w->bench != NULL)
        w->bench->close(w->bench);
    free(w->plant);
    free(w);
}

int xrf_watch_start(struct xrf_shm *shm, const struct xrf_watch_config *cfg, struct xrf_watch **out)
{
    return xrf_watch_start_on(shm, cfg, NULL, out);
}

int xrf_watch_start_on(struct xrf_shm *shm, const struct xrf_watch_config *cfg,
                       struct xrf_ico_transport *bench, struct xrf_watch **out)
{
    if (cfg == NULL || out == NULL || cfg->pid <= 0)
        return -EINVAL;
    /* Refused here, not found out at the moment the outputs must be made safe. */
    if (xrf_safe_reaction_name(cfg->safe_reaction) == NULL)
        return -EINVAL;
    if (cfg->safe_reaction == XRF_SAFE_REACTION_BRAKE &&
        (cfg->brake_channel < 1 || cfg->brake_channel > 4))
        return -EINVAL;
    const struct xrf_plant_ops *ops = NULL;
    const int real = bench != NULL || cfg->spi_device[0] != '\0';
    if (cfg->safe_reaction == XRF_SAFE_REACTION_HOLD && (cfg->force_sim || (real && cfg->plant))) {
        /* A plant the law can hold: one with an arm model (and on the simulated bench a
         * snapshot that fits). */
        ops = xrf_plant_ops(cfg->plant);
        if (ops == NULL || ops->arm == NULL || ops->arm->joints > XRF_HOLD_JOINTS_MAX)
            return -EINVAL;
        if (cfg->force_sim && (ops->load == NULL || ops->snapshot_len <= 0 ||
                               ops->snapshot_len > XRF_SIM_SNAPSHOT_MAX))
            return -EINVAL;
    }
    *out = NULL;
    struct xrf_watch *w = calloc(1, sizeof *w);
    if (w == NULL)
        return -ENOMEM;
    w->shm = shm;
    w->cfg = *cfg;
    w->cfg.spi_device[sizeof w->cfg.spi_device - 1] = '\0';
    w->result.reset_status = XRF_WATCH_RESET_NOT_TRIED;
    w->result.kill_status = -ENOENT;
    w->host_alive_ns = now_ns(); /* starting the watcher is a sign of life */
    if (ops != NULL && shm != NULL && cfg->force_sim) {
        w->plant_ops = ops;
        w->plant = calloc(1, ops->size);
        if (w->plant == NULL) {
            free(w);
            return -ENOMEM;
        }
        ops->init(w->plant); /* touched now: no page fault waiting in the closing sequence */
    }
    /* The boards are opened now, once: nothing is opened (allocated) when the loop is gone. A
     * bench that does not open is tried again when the safe frame is due. */
    int bench_status = 0;
    if (bench != NULL)
        w->bench = bench;
    else if (w->cfg.spi_device[0] != '\0')
        bench_status = xrf_spidev_open(w->cfg.spi_device, w->cfg.spi_speed_hz, &w->bench);
    if (ops != NULL && !cfg->force_sim) {
        int r = w->bench != NULL ? board_hold_setup(w, ops) : bench_status;
        if (r == -EINVAL) {
            w->bench = bench == NULL ? w->bench : NULL; /* the caller's on failure */
            watch_free(w);
            return r;
        }
        if (r < 0) /* the boards did not open: a fault gets the RESET and this reason */
            w->track_status = r;
    }
    /* hold on a bench whose arm the watcher has no model of: it zeroes the outputs (RESET) and
     * says so. */
    w->result.hold_status =
        (cfg->safe_reaction == XRF_SAFE_REACTION_HOLD && w->plant == NULL && w->arm == NULL)
            ? (w->track_status != 0 ? w->track_status : -EOPNOTSUPP)
            : 0;
    w->pidfd = (int)syscall(SYS_pidfd_open, cfg->pid, 0);
    if (w->pidfd < 0) {
        int err = -errno;
        if (bench != NULL)
            w->bench = NULL;
        watch_free(w);
        return err; /* -ESRCH: already gone and reaped; the caller handles the exit itself */
    }
    /* pidfd_open gives no O_CLOEXEC flag of its own on older kernels; no child may keep it. */
    fcntl(w->pidfd, F_SETFD, FD_CLOEXEC);
    w->host_fd = -1;
    if (cfg->host_pid > 0) {
        w->host_fd = (int)syscall(SYS_pidfd_open, cfg->host_pid, 0);
        if (w->host_fd < 0) {
            int err = -errno;
            close(w->pidfd);
            if (bench != NULL)
                w->bench = NULL;
            watch_free(w);
            return err;
        }
        fcntl(w->host_fd, F_SETFD, FD_CLOEXEC);
    }
    w->cancel_fd = eventfd(0, EFD_CLOEXEC);
    if (w->cancel_fd < 0) {
        int err = -errno;
        if (w->host_fd >= 0)
            close(w->host_fd);
        close(w->pidfd);
        if (bench != NULL)
            w->bench = NULL;
        watch_free(w);
        return err;
    }
    pthread_attr_t attr;
    pthread_attr_init(&attr);
    /* Small and touched at once: the thread's stack is no page fault waiting to happen later. */
    pthread_attr_setstacksize(&attr, 64 * 1024);
    int r = pthread_create(&w->thread, &attr, watch_thread, w);
    pthread_attr_destroy(&attr);
    if (r != 0) {
        close(w->cancel_fd);
        if (w->host_fd >= 0)
            close(w->host_fd);
        close(w->pidfd);
        if (bench != NULL)
            w->bench = NULL;
        watch_free(w);
        return -r;
    }
    *out = w;
    return 0;
}

void xrf_watch_host_alive(struct xrf_watch *w, int64_t now)
{
    if (w != NULL)
        __atomic_store_n(&w->host_alive_ns, now, __ATOMIC_RELAXED);
}

int xrf_watch_hold_ready(struct xrf_watch *w, int32_t *channel)
{
    if (w == NULL)
        return -EINVAL;
    if (channel != NULL)
        *channel = 0;
    if (w->arm == NULL)
        return w->cfg.safe_reaction == XRF_SAFE_REACTION_HOLD && w->track_status != 0
                   ? w->track_status
                   : -ENOENT;
    int r = __atomic_load_n(&w->track_status, __ATOMIC_ACQUIRE);
    if (r != 0 && channel != NULL)
        *channel = __atomic_load_n(&w->track_channel, __ATOMIC_RELAXED);
    return r;
}

uint32_t xrf_watch_diagnosis(struct xrf_watch *w, uint8_t *out, uint32_t cap)
{
    if (w == NULL || out == NULL || !__atomic_load_n(&w->done, __ATOMIC_ACQUIRE))
        return 0;
    /* Whole records only: a short buffer gets the first ones. */
    uint32_t len = 0;
    while (len + sizeof(struct xrf_watch_diag_rec) <= w->diag_len) {
        struct xrf_watch_diag_rec rec;
        memcpy(&rec, w->diag + len, sizeof rec);
        uint32_t next = len + (uint32_t)sizeof rec + rec.len;
        if (next > w->diag_len || next > cap)
            break;
        len = next;
    }
    memcpy(out, w->diag, len);
    return len;
}

int xrf_watch_result(struct xrf_watch *w, struct xrf_watch_result *out)
{
    if (w == NULL || out == NULL)
        return -EINVAL;
    if (!__atomic_load_n(&w->done, __ATOMIC_ACQUIRE)) {
        memset(out, 0, sizeof *out);
        out->reason = XRF_WATCH_WATCHING;
        return XRF_WATCH_WATCHING;
    }
    *out = w->result;
    hold_progress(w, out);
    return out->reason;
}

static int watch_end(struct xrf_watch *w, struct xrf_watch_result *out, int cancel)
{
    if (w == NULL)
        return -EINVAL;
    if (cancel) {
        uint64_t one = 1;
        ssize_t n = write(w->cancel_fd, &one, sizeof one);
        (void)n;
    }
    pthread_join(w->thread, NULL);
    if (out != NULL) {
        *out = w->result;
        hold_progress(w, out);
    }
    int reason = w->result.reason;
    close(w->cancel_fd);
    if (w->host_fd >= 0)
        close(w->host_fd);
    close(w->pidfd);
    watch_free(w);
    return reason;
}

int xrf_watch_stop(struct xrf_watch *w, struct xrf_watch_result *out)
{
    return watch_end(w, out, 1);
}

int xrf_watch_wait(struct xrf_watch *w, struct xrf_watch_result *out)
{
    return watch_end(w, out, 0);
}
