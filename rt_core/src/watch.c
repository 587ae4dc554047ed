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
};

static int64_t now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

int xrf_fpga_reset(const char *device, uint32_t speed_hz)
{
    struct xrf_ico_transport *t = NULL;
    int r = xrf_spidev_open(device, speed_hz, &t);
    if (r < 0)
        return r;
    uint8_t tx[XRF_ICO_FRAME], rx[XRF_ICO_FRAME];
    xrf_ico_frame_op(XRF_ICO_RESET, tx);
    r = t->xfer(t, tx, rx);
    t->close(t);
    return r;
}

int xrf_fpga_brake(const char *device, uint32_t speed_hz, int brake_channel)
{
    if (brake_channel < 1 || brake_channel > 4)
        return -EINVAL;
    struct xrf_ico_transport *t = NULL;
    int r = xrf_spidev_open(device, speed_hz, &t);
    if (r < 0)
        return r;
    struct xrf_ico_out out = {{0}, {0}};
    out.dout[brake_channel - 1] = 1;
    uint8_t tx[XRF_ICO_FRAME], rx[XRF_ICO_FRAME];
    xrf_ico_encode_all(&out, 0, tx);
    r = t->xfer(t, tx, rx);
    t->close(t);
    return r;
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
    if (w->cfg.safe_reaction == XRF_SAFE_REACTION_BRAKE)
        return xrf_fpga_brake(w->cfg.spi_device, w->cfg.spi_speed_hz, w->cfg.brake_channel);
    return xrf_fpga_reset(w->cfg.spi_device, w->cfg.spi_speed_hz);
}

/* --- hold on the simulated board ---------------------------------------------------------- */

#define HOLD_TICK_NS 1000000LL /* the law at 1 kHz */
#define HOLD_SUBSTEP_S 100e-6  /* the plant in the board's own sub-steps */
#define HOLD_SEQ_TRIES 1000

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
    for (int ch = 0; ch < 4; ch++)
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
    w->result.hold_phase = xrf_hold_step(&w->hold, q, HOLD_TICK_NS * 1e-9, duty);
    hold_mirror(w, duty);
}

/* The closing sequence to its end: the plant stepped in real time by the duty the law gives
 * each tick, until the law says REST (outputs zero, the arm on its stops). */
static void hold_run(struct xrf_watch *w, double *duty)
{
    struct timespec next;
    clock_gettime(CLOCK_MONOTONIC, &next);
    int64_t last = now_ns();
    while (w->result.hold_phase != XRF_HOLD_PHASE_REST) {
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
        __atomic_store_n(&w->result.drop_urad, (int32_t)lrint(w->hold.drop_max * 1e6),
                         __ATOMIC_RELAXED);
        __atomic_store_n(&w->result.hold_phase, phase, __ATOMIC_RELAXED);
        hold_mirror(w, duty);
    }
    __atomic_store_n(&w->result.rest_ns, now_ns(), __ATOMIC_RELEASE);
}

/* Outputs safe: the simulated board's outputs zeroed (but the brake's) and ignored from now on,
 * the FPGA's likewise. */
static void make_safe(struct xrf_watch *w)
{
    int brake = w->cfg.safe_reaction == XRF_SAFE_REACTION_BRAKE ? w->cfg.brake_channel - 1 : -1;
    if (w->cfg.force_sim && w->shm != NULL) {
        struct xrf_sim_outputs *o = &w->shm->sim;
        /* What the pins show once forced, written before forced_off is published. */
        for (int i = 0; i < 4; i++)
            __atomic_store_n(&o->forced_dout[i], (uint8_t)(i == brake), __ATOMIC_RELAXED);
        __atomic_store_n(&o->forced_off, 1u, __ATOMIC_RELEASE);
        for (int i = 0; i < 4; i++) {
            __atomic_store_n(&o->pwm[i], (int16_t)0, __ATOMIC_RELAXED);
            __atomic_store_n(&o->dout[i], (uint8_t)(i == brake), __ATOMIC_RELAXED);
        }
        w->result.sim_forced = 1;
    }
    if (w->cfg.spi_device[0] != '\0')
        w->result.reset_status = send_safe_frame(w);
}

static void finish(struct xrf_watch *w, int reason, int64_t event_ns)
{
    double duty[XRF_SIM_SNAPSHOT_MAX] = {0};
    int holding = 0;
    if (w->shm != NULL) /* the last cycle's start: the loop ended (or hung) after it */
        w->result.heartbeat_ns = __atomic_load_n(&w->shm->status.heartbeat_ns, __ATOMIC_RELAXED);
    w->result.reason = reason;
    w->result.event_ns = event_ns;
    if (reason == XRF_WATCH_HANG || reason == XRF_WATCH_HOST_GONE) {
        /* Stop it from driving the outputs again before resetting them: a SIGKILLed process
         * runs no more user code. Through the pidfd, so a recycled pid cannot be hit. */
        w->result.kill_status =
            syscall(SYS_pidfd_send_signal, w->pidfd, SIGKILL, NULL, 0) == 0 ? 0 : -errno;
    }
    if (reason == XRF_WATCH_EXIT || reason == XRF_WATCH_HANG || reason == XRF_WATCH_HOST_GONE) {
        make_safe(w); /* the board's own outputs off: from here the watcher drives the plant */
        holding = w->plant != NULL && w->shm != NULL && w->cfg.force_sim;
        if (holding)
            hold_begin(w, duty);
        w->result.safe_ns = now_ns();
    }
    if ((reason == XRF_WATCH_HANG || reason == XRF_WATCH_HOST_GONE) &&
        w->cfg.spi_device[0] != '\0') {
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
    const struct xrf_status *st = w->shm ? &w->shm->status : NULL;
    for (;;) {
        struct pollfd fds[3] = {{.fd = w->pidfd, .events = POLLIN},
                                {.fd = w->cancel_fd, .events = POLLIN},
                                {.fd = w->host_fd, .events = POLLIN}};
        int n = poll(fds, w->host_fd >= 0 ? 3 : 2, timeout_ms);
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
        if (st != NULL && w->cfg.hang_timeout_ns > 0 && !w->cfg.host_only) {
            /* Single aligned words, read without the seqlock: a loop stopped mid-write must
             * not look alive (the seqlock would make it unreadable, never stale). */
            int32_t running = __atomic_load_n(&st->running, __ATOMIC_RELAXED);
            int64_t hb = __atomic_load_n(&st->heartbeat_ns, __ATOMIC_RELAXED);
            w->result.heartbeat_ns = hb;
            if (running && hb > 0 && t - hb > w->cfg.hang_timeout_ns) {
                finish(w, XRF_WATCH_HANG, t);
                return NULL;
            }
        }
    }
}

int xrf_watch_start(struct xrf_shm *shm, const struct xrf_watch_config *cfg, struct xrf_watch **out)
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
    if (cfg->safe_reaction == XRF_SAFE_REACTION_HOLD && cfg->force_sim) {
        /* A plant the law can hold: one with an arm model and a snapshot that fits. */
        ops = xrf_plant_ops(cfg->plant);
        if (ops == NULL || ops->arm == NULL || ops->load == NULL || ops->snapshot_len <= 0 ||
            ops->snapshot_len > XRF_SIM_SNAPSHOT_MAX || ops->arm->joints > XRF_HOLD_JOINTS_MAX)
            return -EINVAL;
    }
    *out = NULL;
    struct xrf_watch *w = calloc(1, sizeof *w);
    if (w == NULL)
        return -ENOMEM;
    if (ops != NULL && shm != NULL) {
        w->plant_ops = ops;
        w->plant = calloc(1, ops->size);
        if (w->plant == NULL) {
            free(w);
            return -ENOMEM;
        }
        ops->init(w->plant); /* touched now: no page fault waiting in the closing sequence */
    }
    w->shm = shm;
    w->cfg = *cfg;
    w->cfg.spi_device[sizeof w->cfg.spi_device - 1] = '\0';
    w->result.reset_status = XRF_WATCH_RESET_NOT_TRIED;
    w->result.kill_status = -ENOENT;
    /* hold on a real board: the law needs the arm's absolute pose, which the watcher cannot
     * read from relative encoders yet; it zeroes the outputs (RESET) and says so. */
    w->result.hold_status =
        (cfg->safe_reaction == XRF_SAFE_REACTION_HOLD && w->plant == NULL) ? -EOPNOTSUPP : 0;
    w->pidfd = (int)syscall(SYS_pidfd_open, cfg->pid, 0);
    if (w->pidfd < 0) {
        int err = -errno;
        free(w->plant);
        free(w);
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
            free(w->plant);
            free(w);
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
        free(w->plant);
        free(w);
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
        free(w->plant);
        free(w);
        return -r;
    }
    *out = w;
    return 0;
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
    if (out != NULL)
        *out = w->result;
    int reason = w->result.reason;
    close(w->cancel_fd);
    if (w->host_fd >= 0)
        close(w->host_fd);
    close(w->pidfd);
    free(w->plant);
    free(w);
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
