/*
 * evl backend: the loop thread runs out-of-band on Xenomai 4 (EVL) through libevl.
 * Built only when CMake finds libevl (XRF_HAVE_EVL); docs/rt_core/evl.md explains the design.
 *
 *  - thread_setup (in-band, may print): pin the CPU *before* evl_attach_self (the core keeps the
 *    thread on the CPU it attaches on; a later sched_setaffinity would demote it), SCHED_FIFO
 *    in-band so it carries over, evl_init (which also does mlockall), the doorbell relay, the
 *    SIGDEBUG counter, evl_attach_self, evl_set_schedattr, EVL_T_WOSS.
 *  - now_ns / sleep_until: EVL monotonic clock (vDSO read, same timebase as CLOCK_MONOTONIC) and
 *    evl_sleep_until with an absolute time.
 *  - ring_doorbell: 8 bytes oob_write()n to an EVL proxy whose target is an eventfd; an in-band
 *    relay thread blocked in read() on that eventfd does the FUTEX_WAKE (xrf_doorbell_wake). The
 *    RT thread never issues an in-band system call for the doorbell.
 *  - demotions: SIGDEBUG (EVL_T_WOSS) deliveries counted by an async-signal-safe handler.
 */
#define _GNU_SOURCE
#include "xrf/backend.h"

#include <errno.h>
#include <pthread.h>
#include <sched.h>
#include <signal.h>
#include <stdio.h>
#include <string.h>
#include <sys/eventfd.h>
#include <time.h>
#include <unistd.h>

#include <evl/evl.h>

/* Newer uapi spells the mode bits EVL_T_*, older ones T_*. */
#if defined(EVL_T_WOSS)
#define XRF_EVL_WOSS EVL_T_WOSS
#elif defined(T_WOSS)
#define XRF_EVL_WOSS T_WOSS
#else
#error "libevl headers define neither EVL_T_WOSS nor T_WOSS"
#endif
/* Report health-monitoring events through SIGDEBUG (the core's default, made explicit). */
#if defined(EVL_T_HMSIG)
#define XRF_EVL_HMSIG EVL_T_HMSIG
#elif defined(T_HMSIG)
#define XRF_EVL_HMSIG T_HMSIG
#else
#define XRF_EVL_HMSIG 0
#endif

#ifndef SIGDEBUG
#define SIGDEBUG SIGXCPU
#endif

#ifndef EVL_CLONE_NONBLOCK
#define EVL_CLONE_NONBLOCK 0
#endif

#define XRF_EVL_BELL_SIZE 8u   /* one eventfd write: a uint64_t */
#define XRF_EVL_BELL_SLOTS 16u /* pending bells the proxy can hold; more just coalesce */

/* ---- state (one loop thread per process) -------------------------------------------------- */

static uint64_t g_demotions;       /* bumped by the SIGDEBUG handler only */
static uint64_t g_bell_dropped;    /* oob_write to the proxy failed (ring full, ...) */
static struct xrf_shm *g_bell_shm; /* set by ring_doorbell, read by the relay */
static int g_efd = -1;             /* our EVL thread element, -1 while not attached */
static int g_bell_evfd = -1;       /* eventfd, the proxy's target */
static int g_bell_proxy = -1;      /* EVL proxy fd the RT side writes to */
static int g_relay_started;
static int g_relay_stop;
static pthread_t g_relay;
static int g_sigaction_saved;
static struct sigaction g_old_sigdebug;
static unsigned g_setup_count;

/* ---- SIGDEBUG: count, nothing else (async-signal-safe: one atomic add) ---------------------- */

static void evl_sigdebug_counter(int sig, siginfo_t *si, void *ctx)
{
    (void)sig;
    (void)si;
    (void)ctx;
    __atomic_add_fetch(&g_demotions, 1u, __ATOMIC_RELAXED);
}

static uint64_t evl_demotions(void)
{
    return __atomic_load_n(&g_demotions, __ATOMIC_RELAXED);
}

static uint64_t evl_doorbell_dropped(void)
{
    return __atomic_load_n(&g_bell_dropped, __ATOMIC_RELAXED);
}

/* ---- clock and sleep ---------------------------------------------------------------------- */

static int64_t evl_now_ns(void)
{
    struct timespec ts;
    /* EVL_CLOCK_MONOTONIC is read through the vDSO: no system call, no mode switch. */
    if (evl_read_clock(EVL_CLOCK_MONOTONIC, &ts) != 0)
        return 0;
    return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

static int evl_backend_sleep_until(int64_t abs_ns)
{
    if (abs_ns < 0)
        abs_ns = 0;
    struct timespec ts = {(time_t)(abs_ns / 1000000000LL), (long)(abs_ns % 1000000000LL)};
    int r;
    do {
        r = evl_sleep_until(EVL_CLOCK_MONOTONIC, &ts); /* 0 or -errno */
    } while (r == -EINTR);
    return r;
}

/* ---- doorbell: proxy -> eventfd -> in-band relay -> futex wake ---------------------------- */

static void evl_ring_doorbell(struct xrf_shm *shm)
{
    /* Plain memory store: the relay picks the pointer up after it is woken. */
    __atomic_store_n(&g_bell_shm, shm, __ATOMIC_RELEASE);
    if (g_bell_proxy < 0) {
        /* Not set up (thread_setup failed or not called): we are in-band anyway. */
        xrf_doorbell_wake(shm);
        return;
    }
    const uint64_t one = 1;
    if (oob_write(g_bell_proxy, &one, sizeof one) != (ssize_t)sizeof one)
        __atomic_add_fetch(&g_bell_dropped, 1u, __ATOMIC_RELAXED); /* bells pending anyway */
}

static void *evl_doorbell_relay(void *arg)
{
    (void)arg;
    for (;;) {
        uint64_t v;
        ssize_t n = read(g_bell_evfd, &v, sizeof v);
        if (__atomic_load_n(&g_relay_stop, __ATOMIC_ACQUIRE))
            break;
        if (n != (ssize_t)sizeof v) {
            if (n < 0 && errno == EINTR)
                continue;
            break; /* the eventfd is gone */
        }
        struct xrf_shm *shm = __atomic_load_n(&g_bell_shm, __ATOMIC_ACQUIRE);
        if (shm)
            xrf_doorbell_wake(shm);
    }
    return NULL;
}

static void evl_doorbell_close(void)
{
    if (g_relay_started) {
        const uint64_t one = 1;
        __atomic_store_n(&g_relay_stop, 1, __ATOMIC_RELEASE);
        if (write(g_bell_evfd, &one, sizeof one) != (ssize_t)sizeof one)
            pthread_cancel(g_relay); /* read() is a cancellation point */
        pthread_join(g_relay, NULL);
        g_relay_started = 0;
    }
    if (g_bell_proxy >= 0) {
        close(g_bell_proxy);
        g_bell_proxy = -1;
    }
    if (g_bell_evfd >= 0) {
        close(g_bell_evfd);
        g_bell_evfd = -1;
    }
}

static int evl_doorbell_open(unsigned instance)
{
    g_bell_evfd = eventfd(0, EFD_CLOEXEC);
    if (g_bell_evfd < 0)
        return -errno;
    /* granularity 8: the proxy relays whole uint64_t writes, which is what eventfd accepts. */
    int pfd = evl_create_proxy(g_bell_evfd, XRF_EVL_BELL_SIZE * XRF_EVL_BELL_SLOTS,
                               XRF_EVL_BELL_SIZE, EVL_CLONE_PRIVATE | EVL_CLONE_NONBLOCK,
                               "xrf-bell:%d.%u", (int)getpid(), instance);
    if (pfd < 0) {
        evl_doorbell_close();
        return pfd;
    }
    g_bell_proxy = pfd;
    g_relay_stop = 0;
    /* The relay is ordinary in-band work: SCHED_OTHER, never the loop's FIFO priority. */
    pthread_attr_t attr;
    struct sched_param sp;
    memset(&sp, 0, sizeof sp);
    pthread_attr_init(&attr);
    pthread_attr_setinheritsched(&attr, PTHREAD_EXPLICIT_SCHED);
    pthread_attr_setschedpolicy(&attr, SCHED_OTHER);
    pthread_attr_setschedparam(&attr, &sp);
    int r = pthread_create(&g_relay, &attr, evl_doorbell_relay, NULL);
    pthread_attr_destroy(&attr);
    if (r != 0) {
        evl_doorbell_close();
        return -r;
    }
    pthread_setname_np(g_relay, "xrf-bell-relay");
    g_relay_started = 1;
    return 0;
}

/* ---- thread set-up and teardown ----------------------------------------------------------- */

/* What to do about a failed evl_init/evl_attach_self: the loop's user reads this once, at start. */
static const char *evl_init_hint(int err)
{
    switch (err) {
    case -EACCES:
        return "this user may not open the EVL devices: /dev/evl/control, /dev/evl/clock/* and "
               "/dev/evl/thread/clone must be readable and writable by it (deploy/udev gives them "
               "to group 'evl', mode 0660: add the user to that group, e.g. `sudo usermod -aG evl "
               "$USER`, and log in again), or run as root";
    case -EPERM:
        return "memory cannot be locked: run as root, or give the user CAP_IPC_LOCK (or an "
               "unlimited memlock limit, LimitMEMLOCK=infinity) and CAP_SYS_NICE";
    case -ENOSYS:
        return "no EVL core in this kernel (it does not know the EVL system calls): boot the EVL "
               "kernel (docs/install/evl-kernel.md), or use XRF_BACKEND=posix";
    case -ENOEXEC:
        return "ABI mismatch between libevl and the kernel: this libevl was built for another EVL "
               "ABI than the running kernel's (/sys/devices/virtual/evl/control/abi); rebuild "
               "libevl against this kernel's uapi";
    case -ENOENT:
    case -ENODEV:
    case -ENXIO:
        return "no EVL core in this kernel (is /dev/evl there? boot the EVL kernel, or use "
               "XRF_BACKEND=posix)";
    default:
        return "see docs/rt_core/evl.md";
    }
}

static int evl_thread_setup(const struct xrf_rt_config *cfg, int *rt_sched)
{
    *rt_sched = 0;
    unsigned instance = ++g_setup_count;

    /* 1. libevl: evl_init also does mlockall(MCL_CURRENT | MCL_FUTURE). */
    int r = evl_init();
    if (r < 0) {
        fprintf(stderr, "xrf: evl backend: evl_init failed: %s (%s)\n", strerror(-r),
                evl_init_hint(r));
        return r;
    }

    /* 2. Doorbell path, created in-band before attaching and before the loop thread is pinned
     * and raised to SCHED_FIFO, so the relay thread stays off the RT CPU. */
    r = evl_doorbell_open(instance);
    if (r < 0) {
        fprintf(stderr, "xrf: evl backend: cannot create the doorbell proxy/relay: %s\n",
                strerror(-r));
        return r;
    }

    /* 3. CPU affinity before attaching (and after the relay exists, which must not inherit
     * it): EVL keeps the thread on the CPU it attaches on; changing the affinity afterwards
     * would demote it. */
    if (cfg->cpu >= 0) {
        cpu_set_t set;
        CPU_ZERO(&set);
        CPU_SET(cfg->cpu, &set);
        if (sched_setaffinity(0, sizeof set, &set) != 0)
            fprintf(stderr,
                    "xrf: warning: cannot pin the loop to CPU %d (%s); it stays on the "
                    "CPU it attaches on\n",
                    cfg->cpu, strerror(errno));
    }

    /* 4. In-band SCHED_FIFO, carried over by evl_attach_self (set explicitly again below). */
    if (cfg->priority > 0) {
        struct sched_param sp;
        memset(&sp, 0, sizeof sp);
        sp.sched_priority = cfg->priority;
        int pr = pthread_setschedparam(pthread_self(), SCHED_FIFO, &sp);
        if (pr != 0)
            fprintf(stderr,
                    "xrf: warning: in-band SCHED_FIFO %d refused (%s); trying "
                    "evl_set_schedattr after attaching\n",
                    cfg->priority, strerror(pr));
    }

    /* 5. Demotion counter: handler first, mode bit after attaching. */
    __atomic_store_n(&g_demotions, 0, __ATOMIC_RELAXED);
    __atomic_store_n(&g_bell_dropped, 0, __ATOMIC_RELAXED);
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sigemptyset(&sa.sa_mask);
    sa.sa_sigaction = evl_sigdebug_counter;
    sa.sa_flags = SA_SIGINFO | SA_RESTART;
    if (sigaction(SIGDEBUG, &sa, &g_old_sigdebug) == 0)
        g_sigaction_saved = 1;

    /* 6. Prefault the stack while page faults are still harmless. */
    if (cfg->stack_prefault > 0) {
        volatile unsigned char *probe = __builtin_alloca(cfg->stack_prefault);
        for (uint32_t i = 0; i < cfg->stack_prefault; i += 4096)
            probe[i] = 0;
    }

    /* 7. Attach, with a name unique on the system. */
    int efd = evl_attach_self("xrf-loop:%d", (int)getpid());
    if (efd == -EEXIST)
        efd = evl_attach_self("xrf-loop:%d.%u", (int)getpid(), instance);
    if (efd < 0) {
        fprintf(stderr, "xrf: evl backend: evl_attach_self failed: %s (%s)\n", strerror(-efd),
                evl_init_hint(efd));
        if (g_sigaction_saved) {
            sigaction(SIGDEBUG, &g_old_sigdebug, NULL);
            g_sigaction_saved = 0;
        }
        evl_doorbell_close();
        return efd;
    }
    g_efd = efd;

    /* 8. EVL scheduling. */
    if (cfg->priority > 0) {
        struct evl_sched_attrs attrs;
        memset(&attrs, 0, sizeof attrs);
        attrs.sched_policy = SCHED_FIFO;
        attrs.sched_priority = cfg->priority;
        r = evl_set_schedattr(efd, &attrs);
        if (r < 0)
            fprintf(stderr, "xrf: WARNING: evl_set_schedattr(SCHED_FIFO %d) failed: %s\n",
                    cfg->priority, strerror(-r));
    }
    struct evl_sched_attrs cur;
    memset(&cur, 0, sizeof cur);
    if (evl_get_schedattr(efd, &cur) == 0 && cur.sched_policy == SCHED_FIFO)
        *rt_sched = 1;
    else
        fprintf(stderr, "xrf: WARNING: the loop thread is attached to EVL without SCHED_FIFO "
                        "(SCHED_OTHER becomes SCHED_WEAK): no timing guarantees. Set XRF_PRIO.\n");

    /* 9. Warn on stage switch: every demotion to in-band raises SIGDEBUG, counted above. */
    r = evl_set_thread_mode(efd, XRF_EVL_WOSS | XRF_EVL_HMSIG, NULL);
    if (r < 0)
        fprintf(stderr, "xrf: warning: cannot enable demotion detection (EVL_T_WOSS): %s\n",
                strerror(-r));
    return 0;
}

static void evl_thread_teardown(void)
{
    if (g_efd >= 0) {
        evl_clear_thread_mode(g_efd, XRF_EVL_WOSS, NULL); /* leaving is not a demotion */
        evl_detach_self();
        g_efd = -1;
    }
    evl_doorbell_close();
    if (g_sigaction_saved) {
        sigaction(SIGDEBUG, &g_old_sigdebug, NULL);
        g_sigaction_saved = 0;
    }
    __atomic_store_n(&g_bell_shm, NULL, __ATOMIC_RELEASE);
}

static const struct xrf_backend evl_backend = {
    .name = "evl",
    .thread_setup = evl_thread_setup,
    .now_ns = evl_now_ns,
    .sleep_until = evl_backend_sleep_until,
    .ring_doorbell = evl_ring_doorbell,
    .demotions = evl_demotions,
    .doorbell_dropped = evl_doorbell_dropped,
    .thread_teardown = evl_thread_teardown,
};

const struct xrf_backend *xrf_backend_evl(void)
{
    return &evl_backend;
}
