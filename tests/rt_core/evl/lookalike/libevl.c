/*
 * EVL LOOK-ALIKE for CI — a stand-in for libevl on plain Linux, NOT libevl (see include/evl/evl.h).
 * Built by tests/rt_core/evl/lookalike/build.sh into <prefix>/lib/libevl.so next to <prefix>/include/evl,
 * the layout of a libevl install under /usr/evl, so rt_core's CMake finds it with
 * -DXRF_EVL_PREFIX=<prefix> and takes its XRF_HAVE_EVL path.
 *
 * What it emulates (docs/rt_core/evl.md, "The EVL look-alike"):
 *  - Threads stay in-band Linux threads; evl_sleep_until is clock_nanosleep(TIMER_ABSTIME),
 *    evl_read_clock is clock_gettime (vDSO), a proxy is a duplicate of its target descriptor that
 *    oob_write writes to at once.
 *  - Stage switches, as the EVL core sees them: an attached thread is "out-of-band" from its
 *    first out-of-band call (evl_sleep_until, oob_*, evl_set_thread_mode, ...) until it enters the
 *    kernel any other way or runs a signal handler. Every system call the attached thread makes
 *    is seen by a seccomp user-notification filter on that thread alone; a supervisor thread
 *    decides: a call issued by this library's own out-of-band services (through xrf_la_sys, whose
 *    address range the filter lets through, or inside a look-alike call) is not a switch;
 *    anything else (write, futex, mmap, ...), and the rt_sigreturn that ends a signal handler, is.
 *    With EVL_T_WOSS set, each switch sends SIGDEBUG to the thread — delivered at its next
 *    look-alike call (so the handler runs in a known place and its own rt_sigreturn is not taken
 *    for another switch). The backend's counter therefore counts what the real core would have
 *    reported, except page faults and the like, which no system call marks.
 *  - On demand, for tests (environment of the loop process):
 *      XRF_EVL_LOOKALIKE_INIT_ERRNO=EACCES|ENOSYS|ENOEXEC|EPERM|...|<number>: evl_init fails so.
 *      XRF_EVL_LOOKALIKE_DEMOTE=N: the first N evl_sleep_until calls with EVL_T_WOSS set each
 *        make one plain system call first (a real switch, seen by the filter like any other).
 *      XRF_EVL_LOOKALIKE_PROXY_REFUSE=N: the first N oob_write()s to a proxy fail with EAGAIN,
 *        as on a full proxy ring.
 *      XRF_EVL_LOOKALIKE_TRACE=1: each switch (thread, system call number) and the moment
 *        EVL_T_WOSS is set are printed to stderr.
 *
 * Limits: x86-64 and aarch64 (the address-range test needs this file's own syscall instruction);
 * elsewhere, or where seccomp is refused, switches are not detected (a note says so at attach).
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <linux/filter.h>
#include <linux/seccomp.h>
#include <pthread.h>
#include <sched.h>
#include <signal.h>
#include <stdarg.h>
#include <stdatomic.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/eventfd.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <sys/prctl.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>

#include <evl/evl.h>

#define LA_EXPORT __attribute__((visibility("default")))

/* ---- the library's own way into the kernel ------------------------------------------------- */

/* xrf_la_sys(nr, a1..a6): the raw system call, returning -errno. Its instructions are the only
 * ones the thread filter lets through without asking the supervisor: what goes through here is
 * the look-alike's out-of-band service (the real core would not leave out-of-band mode for it). */
long xrf_la_sys(long nr, long a1, long a2, long a3, long a4, long a5, long a6);
extern const char xrf_la_sys_end[];
#if defined(__x86_64__)
__asm__(".text\n"
        ".globl xrf_la_sys\n.hidden xrf_la_sys\n.type xrf_la_sys,@function\n"
        "xrf_la_sys:\n"
        "  mov %rdi, %rax\n  mov %rsi, %rdi\n  mov %rdx, %rsi\n  mov %rcx, %rdx\n"
        "  mov %r8, %r10\n  mov %r9, %r8\n  mov 8(%rsp), %r9\n"
        "  syscall\n  ret\n"
        ".globl xrf_la_sys_end\n.hidden xrf_la_sys_end\nxrf_la_sys_end:\n"
        ".size xrf_la_sys, .-xrf_la_sys\n");
#define LA_HAVE_FILTER 1
#elif defined(__aarch64__)
__asm__(".text\n"
        ".globl xrf_la_sys\n.hidden xrf_la_sys\n.type xrf_la_sys,%function\n"
        "xrf_la_sys:\n"
        "  mov x8, x0\n  mov x0, x1\n  mov x1, x2\n  mov x2, x3\n  mov x3, x4\n  mov x4, x5\n"
        "  mov x5, x6\n  svc #0\n  ret\n"
        ".globl xrf_la_sys_end\n.hidden xrf_la_sys_end\nxrf_la_sys_end:\n"
        ".size xrf_la_sys, .-xrf_la_sys\n");
#define LA_HAVE_FILTER 1
#else
long xrf_la_sys(long nr, long a1, long a2, long a3, long a4, long a5, long a6)
{
    long r = syscall(nr, a1, a2, a3, a4, a5, a6);
    return r < 0 ? -errno : r;
}
const char xrf_la_sys_end[1];
#define LA_HAVE_FILTER 0
#endif

#define LA_SYS0(nr) xrf_la_sys((nr), 0, 0, 0, 0, 0, 0)
#define LA_SYS3(nr, a, b, c) xrf_la_sys((nr), (long)(a), (long)(b), (long)(c), 0, 0, 0)
#define LA_SYS4(nr, a, b, c, d) xrf_la_sys((nr), (long)(a), (long)(b), (long)(c), (long)(d), 0, 0)

/* ---- per-thread state ---------------------------------------------------------------------- */

/* Marker in si_value of SIGDEBUG, with the cause in the low bits (the backend counts deliveries). */
#define LA_SIGDEBUG_MARKER 0x5e1f0000
#define LA_CAUSE_SYSCALL 1 /* a plain system call */
#define LA_CAUSE_SIGNAL 2  /* a signal handler ran on the thread */

struct la_thread {
    pid_t tid;
    int efd;                /* the descriptor evl_attach_thread returned (an eventfd) */
    atomic_int attached;
    atomic_int oob;         /* 1 while out-of-band, as the core would see it */
    atomic_int woss;        /* EVL_T_WOSS set */
    atomic_int in_call;     /* inside a look-alike call: its system calls are services */
    atomic_uint pending;    /* SIGDEBUGs owed to the thread */
    atomic_ulong switches;  /* all switches to in-band since attaching (like `evl ps`) */
    int filtered;           /* the seccomp filter is on this thread (for good: filters stay) */
    int handover;           /* pipe the supervisor gets the filter's listener from */
    struct seccomp_notif_sizes sizes;
    char name[64];
};

static __thread struct la_thread *la_self;
static pthread_mutex_t la_lock = PTHREAD_MUTEX_INITIALIZER;
static int la_inited;
static int la_trace;
static atomic_long la_demote_left;
static atomic_long la_refuse_left;

/* Attached thread names: EVL refuses a second element of the same name (-EEXIST). */
#define LA_NOTIF_MAX 512 /* bytes for a seccomp notification or response */

#define LA_MAX_THREADS 64
static char la_names[LA_MAX_THREADS][64];

/* Proxies by descriptor: the proxy descriptor is a duplicate of its target. */
#define LA_MAX_FDS 4096
struct la_proxy {
    unsigned char used;
    size_t granularity;
};
static struct la_proxy la_proxies[LA_MAX_FDS];

static long env_long(const char *name)
{
    const char *v = getenv(name);
    return v && *v ? strtol(v, NULL, 10) : 0;
}

/* ---- switches and SIGDEBUG ----------------------------------------------------------------- */

/* Called by the supervisor while the thread waits in the kernel: memory is quiet. */
static void la_switch_inband(struct la_thread *t, long nr, int cause)
{
    if (!atomic_exchange(&t->oob, 0))
        return; /* already in-band: no switch */
    atomic_fetch_add(&t->switches, 1);
    if (atomic_load(&t->woss))
        atomic_fetch_add(&t->pending, 1);
    if (la_trace) {
        /* No stdio here: the thread may be waiting inside a write while holding stderr's lock. */
        char line[160];
        int n = snprintf(line, sizeof line, "xrf-evl-lookalike: %s switched in-band (%s, system "
                         "call %ld)%s\n", t->name, cause == LA_CAUSE_SIGNAL ? "a signal handler ran"
                         : "a plain system call", nr, atomic_load(&t->woss) ? ", SIGDEBUG" : "");
        if (n > 0 && write(STDERR_FILENO, line, (size_t)n) < 0)
            return;
    }
}

/* With XRF_EVL_LOOKALIKE_TRACE: one line on stderr, written directly (tests read the order). */
static void la_note(const struct la_thread *t, const char *what)
{
    if (!la_trace)
        return;
    char line[160];
    int n = snprintf(line, sizeof line, "xrf-evl-lookalike: %s: %s\n", t->name, what);
    if (n > 0 && write(STDERR_FILENO, line, (size_t)n) < 0)
        return;
}

/* SIGDEBUG for every switch not yet reported, sent by the thread to itself through xrf_la_sys:
 * the handler runs on the way back from that call, while in_call is set and oob is 0. */
static void la_deliver(struct la_thread *t)
{
    unsigned n = atomic_exchange(&t->pending, 0);
    for (; n > 0; n--) {
        siginfo_t si;
        memset(&si, 0, sizeof si);
        si.si_signo = SIGDEBUG;
        si.si_code = SI_QUEUE;
        si.si_pid = getpid();
        si.si_uid = getuid();
        si.si_value.sival_int = LA_SIGDEBUG_MARKER | LA_CAUSE_SYSCALL;
        LA_SYS4(SYS_rt_tgsigqueueinfo, getpid(), t->tid, SIGDEBUG, &si);
    }
}

/* Entry of every look-alike call made by an attached thread; `oob_call`: the call is an
 * out-of-band one, which brings a demoted thread back out-of-band. */
static struct la_thread *la_enter(int oob_call)
{
    struct la_thread *t = la_self;
    if (t == NULL)
        return NULL;
    atomic_store(&t->in_call, 1);
    la_deliver(t);
    if (oob_call && atomic_load(&t->attached))
        atomic_store(&t->oob, 1);
    return t;
}

static void la_leave(struct la_thread *t)
{
    if (t != NULL)
        atomic_store(&t->in_call, 0);
}

#if LA_HAVE_FILTER
/* The supervisor never allocates, locks or uses stdio once the filter is on: the thread it
 * serves may be stopped inside malloc or printf, holding their locks, until it answers. */
static void *la_supervisor(void *arg)
{
    struct la_thread *t = arg;
    int pipefd = t->handover;
    int listener = -1;
    const struct seccomp_notif_sizes sizes = t->sizes;
    _Alignas(16) unsigned char req_buf[LA_NOTIF_MAX], resp_buf[LA_NOTIF_MAX];
    struct seccomp_notif *req = (struct seccomp_notif *)req_buf;
    struct seccomp_notif_resp *resp = (struct seccomp_notif_resp *)resp_buf;
    if (read(pipefd, &listener, sizeof listener) != (ssize_t)sizeof listener)
        return NULL;
    close(pipefd);
    if (listener < 0)
        return NULL;
    for (;;) {
        memset(req, 0, sizes.seccomp_notif);
        if (ioctl(listener, SECCOMP_IOCTL_NOTIF_RECV, req) != 0) {
            if (errno == EINTR || errno == ENOENT)
                continue;
            break;
        }
        /* Threads the attached one creates inherit the filter; they are not attached. */
        if ((pid_t)req->pid == t->tid && atomic_load(&t->attached)) {
            if (req->data.nr == SYS_rt_sigreturn)
                la_switch_inband(t, req->data.nr, LA_CAUSE_SIGNAL);
            else if (!atomic_load(&t->in_call))
                la_switch_inband(t, req->data.nr, LA_CAUSE_SYSCALL);
        }
        memset(resp, 0, sizes.seccomp_notif_resp);
        resp->id = req->id;
        resp->flags = SECCOMP_USER_NOTIF_FLAG_CONTINUE;
        ioctl(listener, SECCOMP_IOCTL_NOTIF_SEND, resp); /* ENOENT: the call was interrupted */
    }
    return NULL;
}

/* Puts the calling thread under the filter: system calls from outside [xrf_la_sys,
 * xrf_la_sys_end) go to the supervisor, which lets each continue after noting it. */
static int la_install_filter(struct la_thread *t)
{
    const uint64_t lo = (uint64_t)(uintptr_t)xrf_la_sys, hi = (uint64_t)(uintptr_t)xrf_la_sys_end;
    if ((lo >> 32) != (hi >> 32))
        return -ERANGE;
    const unsigned ip_lo = (unsigned)offsetof(struct seccomp_data, instruction_pointer);
    struct sock_filter code[] = {
        BPF_STMT(BPF_LD | BPF_W | BPF_ABS, ip_lo + 4),               /* 0: ip, high word */
        BPF_JUMP(BPF_JMP | BPF_JEQ | BPF_K, (uint32_t)(lo >> 32), 0, 4), /* 1: else notify */
        BPF_STMT(BPF_LD | BPF_W | BPF_ABS, ip_lo),                   /* 2: ip, low word */
        BPF_JUMP(BPF_JMP | BPF_JGE | BPF_K, (uint32_t)lo, 0, 2),     /* 3: below: notify */
        BPF_JUMP(BPF_JMP | BPF_JGE | BPF_K, (uint32_t)hi, 1, 0),     /* 4: above: notify */
        BPF_STMT(BPF_RET | BPF_K, SECCOMP_RET_ALLOW),                /* 5 */
        BPF_STMT(BPF_RET | BPF_K, SECCOMP_RET_USER_NOTIF),           /* 6 */
    };
    struct sock_fprog prog = {(unsigned short)(sizeof code / sizeof code[0]), code};
    if (syscall(SYS_seccomp, SECCOMP_GET_NOTIF_SIZES, 0, &t->sizes) != 0)
        return -errno;
    if (t->sizes.seccomp_notif > LA_NOTIF_MAX || t->sizes.seccomp_notif_resp > LA_NOTIF_MAX)
        return -EOVERFLOW;
    int pipefd[2];
    if (pipe2(pipefd, O_CLOEXEC) != 0)
        return -errno;
    /* The supervisor first: a thread created after the filter would inherit it. */
    t->handover = pipefd[0];
    pthread_t sup;
    pthread_attr_t attr;
    pthread_attr_init(&attr);
    pthread_attr_setdetachstate(&attr, PTHREAD_CREATE_DETACHED);
    pthread_attr_setinheritsched(&attr, PTHREAD_EXPLICIT_SCHED);
    pthread_attr_setschedpolicy(&attr, SCHED_OTHER);
    struct sched_param sp = {0};
    pthread_attr_setschedparam(&attr, &sp);
    int r = pthread_create(&sup, &attr, la_supervisor, t);
    pthread_attr_destroy(&attr);
    if (r != 0) {
        close(pipefd[0]);
        close(pipefd[1]);
        return -r;
    }
    pthread_setname_np(sup, "evl-lookalike");
    long fd = syscall(SYS_seccomp, SECCOMP_SET_MODE_FILTER, SECCOMP_FILTER_FLAG_NEW_LISTENER, &prog);
    if (fd < 0 && errno == EACCES) {
        /* Unprivileged: a filter needs no_new_privs (this thread never execs anyway). */
        prctl(PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0);
        fd = syscall(SYS_seccomp, SECCOMP_SET_MODE_FILTER, SECCOMP_FILTER_FLAG_NEW_LISTENER, &prog);
    }
    int listener = fd < 0 ? -1 : (int)fd;
    int err = fd < 0 ? -errno : 0;
    /* Handed over through xrf_la_sys: a plain write would already wait for the supervisor. */
    LA_SYS3(SYS_write, pipefd[1], &listener, sizeof listener);
    LA_SYS3(SYS_close, pipefd[1], 0, 0);
    return err;
}
#endif

/* ---- init, threads ------------------------------------------------------------------------- */

static int errno_from_env(const char *v)
{
    static const struct {
        const char *name;
        int value;
    } names[] = {{"EPERM", EPERM},   {"EACCES", EACCES}, {"ENOSYS", ENOSYS}, {"ENOEXEC", ENOEXEC},
                 {"ENOENT", ENOENT}, {"ENODEV", ENODEV}, {"ENXIO", ENXIO},   {"ENOMEM", ENOMEM}};
    for (size_t i = 0; i < sizeof names / sizeof names[0]; i++)
        if (strcmp(v, names[i].name) == 0)
            return names[i].value;
    long x = strtol(v, NULL, 10);
    return (int)(x < 0 ? -x : x);
}

LA_EXPORT int evl_init(void)
{
    const char *fail = getenv("XRF_EVL_LOOKALIKE_INIT_ERRNO");
    if (fail && *fail) {
        int e = errno_from_env(fail);
        if (e > 0)
            return -e;
    }
    pthread_mutex_lock(&la_lock);
    if (!la_inited) {
        la_inited = 1;
        la_trace = env_long("XRF_EVL_LOOKALIKE_TRACE") != 0;
        atomic_store(&la_demote_left, env_long("XRF_EVL_LOOKALIKE_DEMOTE"));
        atomic_store(&la_refuse_left, env_long("XRF_EVL_LOOKALIKE_PROXY_REFUSE"));
        /* libevl locks memory here and fails without the right to; the look-alike runs as any
         * CI user, so it only says so. */
        if (mlockall(MCL_CURRENT | MCL_FUTURE) != 0)
            fprintf(stderr, "xrf-evl-lookalike: mlockall failed (%s); real libevl's evl_init "
                            "would fail here\n", strerror(errno));
    }
    pthread_mutex_unlock(&la_lock);
    return 0;
}

LA_EXPORT int evl_attach_thread(int flags, const char *fmt, ...)
{
    (void)flags;
    if (la_self && atomic_load(&la_self->attached))
        return -EBUSY;
    int r = evl_init();
    if (r < 0)
        return r;
    char name[64];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(name, sizeof name, fmt, ap);
    va_end(ap);
    pthread_mutex_lock(&la_lock);
    int slot = -1;
    for (int i = 0; i < LA_MAX_THREADS; i++) {
        if (la_names[i][0] && strcmp(la_names[i], name) == 0) {
            pthread_mutex_unlock(&la_lock);
            return -EEXIST;
        }
        if (!la_names[i][0] && slot < 0)
            slot = i;
    }
    if (slot < 0) {
        pthread_mutex_unlock(&la_lock);
        return -EAGAIN;
    }
    snprintf(la_names[slot], sizeof la_names[slot], "%s", name);
    pthread_mutex_unlock(&la_lock);

    struct la_thread *t = la_self;
    if (t == NULL) {
        t = calloc(1, sizeof *t); /* kept for the thread's life: the supervisor reads it */
        if (t == NULL)
            return -ENOMEM;
        t->tid = (pid_t)syscall(SYS_gettid);
        t->handover = -1;
    }
    snprintf(t->name, sizeof t->name, "%s", name);
    t->efd = eventfd(0, EFD_CLOEXEC);
    if (t->efd < 0) {
        int e = -errno;
        la_names[slot][0] = '\0';
        if (la_self == NULL)
            free(t);
        return e;
    }
    atomic_store(&t->oob, 0); /* attached in-band; the first out-of-band call switches */
    atomic_store(&t->woss, 0);
    atomic_store(&t->pending, 0);
    atomic_store(&t->switches, 0);
    atomic_store(&t->attached, 1);
    la_self = t;
#if LA_HAVE_FILTER
    if (!t->filtered) {
        int fr = la_install_filter(t);
        if (fr == 0)
            t->filtered = 1;
        else
            fprintf(stderr, "xrf-evl-lookalike: no seccomp filter (%s): switches to in-band are "
                            "not detected\n", strerror(-fr));
    }
#else
    fprintf(stderr, "xrf-evl-lookalike: this architecture has no switch detection\n");
#endif
    return t->efd;
}

LA_EXPORT int evl_detach_self(void)
{
    struct la_thread *t = la_enter(0);
    if (t == NULL || !atomic_load(&t->attached)) {
        la_leave(t);
        return -EPERM;
    }
    atomic_store(&t->attached, 0);
    atomic_store(&t->oob, 0);
    atomic_store(&t->woss, 0);
    pthread_mutex_lock(&la_lock);
    for (int i = 0; i < LA_MAX_THREADS; i++)
        if (strcmp(la_names[i], t->name) == 0)
            la_names[i][0] = '\0';
    pthread_mutex_unlock(&la_lock);
    close(t->efd);
    t->efd = -1;
    la_leave(t);
    return 0;
}

LA_EXPORT int evl_get_self(void)
{
    struct la_thread *t = la_self;
    return t && atomic_load(&t->attached) ? t->efd : -EPERM;
}

static int la_check_self(struct la_thread *t, int efd)
{
    if (t == NULL || !atomic_load(&t->attached))
        return -EPERM;
    return efd == t->efd ? 0 : -EBADF; /* only the caller's own element is supported */
}

LA_EXPORT int evl_set_thread_mode(int efd, int mask, int *oldmask)
{
    struct la_thread *t = la_enter(1);
    int r = la_check_self(t, efd);
    if (r == 0) {
        if (oldmask)
            *oldmask = atomic_load(&t->woss) ? EVL_T_WOSS : 0;
        if (mask & EVL_T_WOSS) {
            atomic_store(&t->woss, 1);
            la_note(t, "stage-switch warnings on (EVL_T_WOSS)");
        }
    }
    la_leave(t);
    return r;
}

LA_EXPORT int evl_clear_thread_mode(int efd, int mask, int *oldmask)
{
    struct la_thread *t = la_enter(1); /* switches owed so far are reported first */
    int r = la_check_self(t, efd);
    if (r == 0) {
        if (oldmask)
            *oldmask = atomic_load(&t->woss) ? EVL_T_WOSS : 0;
        if (mask & EVL_T_WOSS)
            atomic_store(&t->woss, 0);
    }
    la_leave(t);
    return r;
}

LA_EXPORT int evl_switch_oob(void)
{
    struct la_thread *t = la_enter(1);
    int r = t && atomic_load(&t->attached) ? 0 : -EPERM;
    la_leave(t);
    return r;
}

LA_EXPORT int evl_switch_inband(void)
{
    struct la_thread *t = la_enter(0);
    if (t)
        atomic_store(&t->oob, 0); /* asked for: not a switch the core warns about */
    la_leave(t);
    return 0;
}

LA_EXPORT bool evl_is_inband(void)
{
    struct la_thread *t = la_self;
    return !(t && atomic_load(&t->attached) && atomic_load(&t->oob));
}

/* ---- scheduling ---------------------------------------------------------------------------- */

LA_EXPORT int evl_set_schedattr(int efd, const struct evl_sched_attrs *attrs)
{
    struct la_thread *t = la_enter(1);
    int r = la_check_self(t, efd);
    if (r == 0) {
        struct sched_param sp = {0};
        int policy = attrs->sched_policy;
        if (policy == SCHED_WEAK)
            policy = SCHED_OTHER;
        else
            sp.sched_priority = attrs->sched_priority;
        r = -pthread_setschedparam(pthread_self(), policy, &sp);
    }
    la_leave(t);
    return r;
}

LA_EXPORT int evl_get_schedattr(int efd, struct evl_sched_attrs *attrs)
{
    struct la_thread *t = la_enter(1);
    int r = la_check_self(t, efd);
    if (r == 0) {
        int policy = SCHED_OTHER;
        struct sched_param sp = {0};
        r = -pthread_getschedparam(pthread_self(), &policy, &sp);
        memset(attrs, 0, sizeof *attrs);
        /* What an attached thread gets on EVL: SCHED_FIFO/RR carried over, else SCHED_WEAK. */
        attrs->sched_policy = policy == SCHED_FIFO || policy == SCHED_RR ? policy : SCHED_WEAK;
        attrs->sched_priority = sp.sched_priority;
    }
    la_leave(t);
    return r;
}

LA_EXPORT int evl_yield(void)
{
    struct la_thread *t = la_enter(1);
    LA_SYS0(SYS_sched_yield);
    la_leave(t);
    return 0;
}

/* ---- clocks -------------------------------------------------------------------------------- */

static int la_clock(int clockfd, clockid_t *out)
{
    if (clockfd == EVL_CLOCK_MONOTONIC)
        *out = CLOCK_MONOTONIC;
    else if (clockfd == EVL_CLOCK_REALTIME)
        *out = CLOCK_REALTIME;
    else
        return -EBADF;
    return 0;
}

LA_EXPORT int evl_read_clock(int clockfd, struct timespec *tp)
{
    clockid_t c;
    int r = la_clock(clockfd, &c);
    if (r)
        return r;
    struct la_thread *t = la_enter(0); /* a vDSO read on EVL: no mode change either way */
    r = clock_gettime(c, tp) == 0 ? 0 : -errno;
    la_leave(t);
    return r;
}

LA_EXPORT int evl_get_clock_resolution(int clockfd, struct timespec *tp)
{
    clockid_t c;
    int r = la_clock(clockfd, &c);
    if (r)
        return r;
    struct la_thread *t = la_enter(0);
    r = clock_getres(c, tp) == 0 ? 0 : -errno;
    la_leave(t);
    return r;
}

LA_EXPORT int evl_sleep_until(int clockfd, const struct timespec *timeout)
{
    clockid_t c;
    int r = la_clock(clockfd, &c);
    if (r)
        return r;
    struct la_thread *t = la_enter(1);
    if (t && atomic_load(&t->woss) && atomic_load(&la_demote_left) > 0 &&
        atomic_fetch_sub(&la_demote_left, 1) > 0) {
        /* A switch asked for by a test: one plain system call from the out-of-band thread. */
        atomic_store(&t->in_call, 0);
        syscall(SYS_getppid);
        atomic_store(&t->in_call, 1);
        la_deliver(t);
        atomic_store(&t->oob, 1);
    }
    r = (int)LA_SYS4(SYS_clock_nanosleep, c, TIMER_ABSTIME, timeout, NULL);
    la_leave(t);
    return r; /* 0 or -errno (-EINTR when a signal handler ran) */
}

LA_EXPORT int evl_usleep(useconds_t usecs)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    ts.tv_sec += usecs / 1000000;
    ts.tv_nsec += (long)(usecs % 1000000) * 1000;
    if (ts.tv_nsec >= 1000000000L) {
        ts.tv_nsec -= 1000000000L;
        ts.tv_sec++;
    }
    return evl_sleep_until(EVL_CLOCK_MONOTONIC, &ts);
}

LA_EXPORT int evl_udelay(unsigned int usecs)
{
    struct timespec t0, now;
    clock_gettime(CLOCK_MONOTONIC, &t0);
    const long long end = (long long)t0.tv_sec * 1000000000LL + t0.tv_nsec + usecs * 1000LL;
    do
        clock_gettime(CLOCK_MONOTONIC, &now);
    while ((long long)now.tv_sec * 1000000000LL + now.tv_nsec < end);
    return 0;
}

/* ---- proxies and out-of-band I/O ----------------------------------------------------------- */

LA_EXPORT int evl_create_proxy(int targetfd, size_t bufsz, size_t granularity, int flags,
                               const char *fmt, ...)
{
    (void)flags;
    (void)fmt;
    if (bufsz == 0 || granularity > bufsz || (granularity && bufsz % granularity))
        return -EINVAL;
    int fd = fcntl(targetfd, F_DUPFD_CLOEXEC, 0);
    if (fd < 0)
        return -errno;
    if (fd >= LA_MAX_FDS) {
        close(fd);
        return -EMFILE;
    }
    la_proxies[fd].used = 1;
    la_proxies[fd].granularity = granularity ? granularity : 1;
    return fd;
}

LA_EXPORT ssize_t oob_write(int efd, const void *buf, size_t count)
{
    struct la_thread *t = la_enter(1);
    ssize_t r;
    if (efd >= 0 && efd < LA_MAX_FDS && la_proxies[efd].used) {
        if (count % la_proxies[efd].granularity) {
            la_leave(t);
            errno = EINVAL;
            return -1;
        }
        if (atomic_load(&la_refuse_left) > 0 && atomic_fetch_sub(&la_refuse_left, 1) > 0) {
            la_leave(t);
            errno = EAGAIN; /* the proxy's ring is full */
            return -1;
        }
    }
    r = LA_SYS3(SYS_write, efd, buf, count);
    la_leave(t);
    if (r < 0) {
        errno = (int)-r;
        return -1;
    }
    return r;
}

LA_EXPORT ssize_t oob_read(int efd, void *buf, size_t count)
{
    struct la_thread *t = la_enter(1);
    ssize_t r = LA_SYS3(SYS_read, efd, buf, count);
    la_leave(t);
    if (r < 0) {
        errno = (int)-r;
        return -1;
    }
    return r;
}

LA_EXPORT int oob_ioctl(int efd, unsigned long request, ...)
{
    va_list ap;
    va_start(ap, request);
    long arg = va_arg(ap, long);
    va_end(ap);
    struct la_thread *t = la_enter(1);
    long r = LA_SYS3(SYS_ioctl, efd, request, arg);
    la_leave(t);
    if (r < 0) {
        errno = (int)-r;
        return -1;
    }
    return (int)r;
}

/* stdout "through a proxy": one write of the formatted text, as an out-of-band service. */
LA_EXPORT int evl_vprintf(const char *fmt, va_list ap)
{
    char buf[1024];
    int n = vsnprintf(buf, sizeof buf, fmt, ap);
    if (n < 0)
        return -EINVAL;
    if ((size_t)n >= sizeof buf)
        n = (int)sizeof buf - 1;
    struct la_thread *t = la_enter(1);
    long r = LA_SYS3(SYS_write, STDOUT_FILENO, buf, (size_t)n);
    la_leave(t);
    return r < 0 ? (int)r : n;
}

LA_EXPORT int evl_printf(const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    int n = evl_vprintf(fmt, ap);
    va_end(ap);
    return n;
}
