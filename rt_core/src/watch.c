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
    /* Written by the watcher thread only, read by the host after `done` (acquire/release). */
    struct xrf_watch_result result;
    uint32_t done;
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
    if (w->cfg.spi_device[0] != '\0')
        w->result.reset_status = send_safe_frame(w);
}

static void finish(struct xrf_watch *w, int reason, int64_t event_ns)
{
    if (w->shm != NULL) /* the last cycle's start: the loop ended (or hung) after it */
        w->result.heartbeat_ns = __atomic_load_n(&w->shm->status.heartbeat_ns, __ATOMIC_RELAXED);
    w->result.reason = reason;
    w->result.event_ns = event_ns;
    if (reason == XRF_WATCH_HANG) {
        /* Stop it from driving the outputs again before resetting them: a SIGKILLed process
         * runs no more user code. Through the pidfd, so a recycled pid cannot be hit. */
        w->result.kill_status =
            syscall(SYS_pidfd_send_signal, w->pidfd, SIGKILL, NULL, 0) == 0 ? 0 : -errno;
    }
    if (reason == XRF_WATCH_EXIT || reason == XRF_WATCH_HANG) {
        make_safe(w);
        w->result.safe_ns = now_ns();
    }
    if (reason == XRF_WATCH_HANG && w->cfg.spi_device[0] != '\0') {
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
        struct pollfd fds[2] = {{.fd = w->pidfd, .events = POLLIN},
                                {.fd = w->cancel_fd, .events = POLLIN}};
        int n = poll(fds, 2, timeout_ms);
        int64_t t = now_ns();
        /* The exit comes first: a cancel that races with it still gets the outputs made safe. */
        if (n > 0 && (fds[0].revents & (POLLIN | POLLHUP | POLLERR))) {
            finish(w, XRF_WATCH_EXIT, t);
            return NULL;
        }
        if (n > 0 && (fds[1].revents & POLLIN)) {
            finish(w, XRF_WATCH_CANCELLED, t);
            return NULL;
        }
        if (st != NULL && w->cfg.hang_timeout_ns > 0) {
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
    *out = NULL;
    struct xrf_watch *w = calloc(1, sizeof *w);
    if (w == NULL)
        return -ENOMEM;
    w->shm = shm;
    w->cfg = *cfg;
    w->cfg.spi_device[sizeof w->cfg.spi_device - 1] = '\0';
    w->result.reset_status = XRF_WATCH_RESET_NOT_TRIED;
    w->result.kill_status = -ENOENT;
    w->pidfd = (int)syscall(SYS_pidfd_open, cfg->pid, 0);
    if (w->pidfd < 0) {
        int err = -errno;
        free(w);
        return err; /* -ESRCH: already gone and reaped; the caller handles the exit itself */
    }
    /* pidfd_open gives no O_CLOEXEC flag of its own on older kernels; no child may keep it. */
    fcntl(w->pidfd, F_SETFD, FD_CLOEXEC);
    w->cancel_fd = eventfd(0, EFD_CLOEXEC);
    if (w->cancel_fd < 0) {
        int err = -errno;
        close(w->pidfd);
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
        close(w->pidfd);
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

int xrf_watch_stop(struct xrf_watch *w, struct xrf_watch_result *out)
{
    if (w == NULL)
        return -EINVAL;
    uint64_t one = 1;
    ssize_t n = write(w->cancel_fd, &one, sizeof one);
    (void)n;
    pthread_join(w->thread, NULL);
    if (out != NULL)
        *out = w->result;
    int reason = w->result.reason;
    close(w->cancel_fd);
    close(w->pidfd);
    free(w);
    return reason;
}
