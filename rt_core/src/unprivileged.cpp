// A loop process without the privileges an XRF2 main assumes (unprivileged.h).
//
// XRF2's main() calls evl_init() and mlockall(MCL_CURRENT | MCL_FUTURE), then creates the loop
// thread with an explicit SCHED_FIFO policy. As a normal user (RLIMIT_MEMLOCK 8 MiB, RLIMIT_RTPRIO
// 0) both fail: with MCL_FUTURE every new mapping must be locked within the limit, so the 8 MiB
// default thread stack does not fit and pthread_create() answers EAGAIN; and SCHED_FIFO is
// refused with EPERM. The main then exits through error(), although the loop would run fine
// without either (the posix backend runs without real-time scheduling and says so).
//
// So the runtime defines pthread_create() for the controller's executable (a static library's
// definition wins over libc's for every call in it; libc's is found with dlsym(RTLD_NEXT)). It
// calls the real one and only when that fails for one of these two reasons retries without
// what was refused, with a warning on stderr: EAGAIN while memory is locked under a finite
// limit -> munlockall() (locking off for the process); EPERM on a thread asking for
// SCHED_FIFO/RR -> the same thread with the creator's scheduling. Any other outcome is
// returned unchanged, and a process that has the privileges never sees a difference.
#include "unprivileged.h"

#include <atomic>
#include <cerrno>
#include <climits>
#include <cstdio>
#include <cstring>
#include <dlfcn.h>
#include <linux/capability.h>
#include <pthread.h>
#include <sched.h>
#include <sys/mman.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

namespace xrf
{

namespace
{

std::atomic<int> g_refused_priority{0};
std::atomic<bool> g_locking_off{false};

bool hasCapIpcLock()
{
    __user_cap_header_struct header{};
    header.version = _LINUX_CAPABILITY_VERSION_3;
    __user_cap_data_struct data[2]{};
    if (syscall(SYS_capget, &header, data) != 0)
        return false;
    return (data[CAP_IPC_LOCK / 32].effective & (1u << (CAP_IPC_LOCK % 32))) != 0;
}

// /proc/self/status "VmSize:" in bytes (what mlockall(MCL_CURRENT) must lock), 0 if unknown.
size_t mappedBytes()
{
    FILE *f = std::fopen("/proc/self/status", "re");
    if (f == nullptr)
        return 0;
    char line[256];
    unsigned long kb = 0;
    while (std::fgets(line, sizeof line, f) != nullptr)
        if (std::sscanf(line, "VmSize: %lu kB", &kb) == 1)
            break;
    std::fclose(f);
    return (size_t)kb * 1024;
}

bool anythingLocked()
{
    FILE *f = std::fopen("/proc/self/status", "re");
    if (f == nullptr)
        return true;
    char line[256];
    unsigned long kb = 0;
    while (std::fgets(line, sizeof line, f) != nullptr)
        if (std::sscanf(line, "VmLck: %lu kB", &kb) == 1)
            break;
    std::fclose(f);
    return kb > 0;
}

void switchLockingOff(const char *why)
{
    munlockall();
    if (!g_locking_off.exchange(true))
        std::fprintf(
            stderr,
            "xrf: WARNING: memory is NOT locked (%s; RLIMIT_MEMLOCK is %zu KiB and this user may "
            "not raise it): the loop runs, but page faults may add latency. The appliance's run "
            "sandbox and deploy/ grant the limit; by hand: ulimit -l unlimited, or CAP_IPC_LOCK "
            "(docs/rt_core/runtime.md).\n",
            why, memlockLimit() / 1024);
}

using CreateFn = int (*)(pthread_t *, const pthread_attr_t *, void *(*)(void *), void *);

CreateFn realCreate()
{
    static std::atomic<CreateFn> real{nullptr};
    CreateFn fn = real.load(std::memory_order_acquire);
    if (fn == nullptr) {
        fn = reinterpret_cast<CreateFn>(dlsym(RTLD_NEXT, "pthread_create"));
        real.store(fn, std::memory_order_release);
    }
    return fn;
}

// `attr` with the creator's scheduling instead of its explicit SCHED_FIFO/RR; everything else
// that pthread attributes carry (stack, guard, detach state, CPU affinity, scope) kept.
int createInheriting(CreateFn real, pthread_t *thread, const pthread_attr_t *attr,
                     void *(*start)(void *), void *arg)
{
    pthread_attr_t copy;
    pthread_attr_init(&copy);
    int detach = 0, scope = 0;
    size_t size = 0;
    void *addr = nullptr;
    if (pthread_attr_getdetachstate(attr, &detach) == 0)
        pthread_attr_setdetachstate(&copy, detach);
    if (pthread_attr_getscope(attr, &scope) == 0)
        pthread_attr_setscope(&copy, scope);
    if (pthread_attr_getguardsize(attr, &size) == 0)
        pthread_attr_setguardsize(&copy, size);
    if (pthread_attr_getstack(attr, &addr, &size) == 0 && addr != nullptr)
        pthread_attr_setstack(&copy, addr, size);
    else if (pthread_attr_getstacksize(attr, &size) == 0)
        pthread_attr_setstacksize(&copy, size);
    cpu_set_t cpus;
    CPU_ZERO(&cpus);
    if (pthread_attr_getaffinity_np(attr, sizeof cpus, &cpus) == 0 && CPU_COUNT(&cpus) > 0)
        pthread_attr_setaffinity_np(&copy, sizeof cpus, &cpus);
    pthread_attr_setinheritsched(&copy, PTHREAD_INHERIT_SCHED);
    int r = real(thread, &copy, start, arg);
    pthread_attr_destroy(&copy);
    return r;
}

} // namespace

size_t memlockLimit()
{
    rlimit rl{};
    if (getrlimit(RLIMIT_MEMLOCK, &rl) != 0 || rl.rlim_cur == RLIM_INFINITY)
        return (size_t)-1;
    return (size_t)rl.rlim_cur;
}

size_t memlockHeadroom()
{
    const size_t limit = memlockLimit();
    if (limit == (size_t)-1 || hasCapIpcLock())
        return (size_t)-1;
    const size_t mapped = mappedBytes();
    return mapped >= limit ? 0 : limit - mapped;
}

bool fitMemoryLocking(size_t need, bool quiet)
{
    if (g_locking_off.load())
        return false;
    const size_t headroom = memlockHeadroom();
    if (headroom == (size_t)-1 || headroom >= need)
        return true;
    if (quiet)
        g_locking_off.store(true); // warned about once, by whoever is not quiet
    char why[160];
    std::snprintf(why, sizeof why, "the loop maps about %zu KiB more than the limit leaves",
                  need / 1024);
    switchLockingOff(why);
    return false;
}

int refusedThreadPriority()
{
    return g_refused_priority.load();
}

} // namespace xrf

extern "C" int pthread_create(pthread_t *__restrict thread, const pthread_attr_t *__restrict attr,
                              void *(*start)(void *), void *__restrict arg) noexcept
{
    xrf::CreateFn real = xrf::realCreate();
    if (real == nullptr)
        return EAGAIN;
    int r = real(thread, attr, start, arg);
    if (r == EAGAIN && xrf::memlockHeadroom() != (size_t)-1 && xrf::anythingLocked()) {
        // The new stack had to be locked (MCL_FUTURE) and did not fit under the limit.
        xrf::switchLockingOff("a new thread's stack could not be locked");
        r = real(thread, attr, start, arg);
    }
    if (r == EPERM && attr != nullptr) {
        int inherit = PTHREAD_INHERIT_SCHED, policy = SCHED_OTHER;
        sched_param sp{};
        pthread_attr_getinheritsched(attr, &inherit);
        pthread_attr_getschedpolicy(attr, &policy);
        pthread_attr_getschedparam(attr, &sp);
        if (inherit == PTHREAD_EXPLICIT_SCHED && (policy == SCHED_FIFO || policy == SCHED_RR)) {
            r = xrf::createInheriting(real, thread, attr, start, arg);
            if (r == 0) {
                xrf::g_refused_priority.store(sp.sched_priority > 0 ? sp.sched_priority : 1);
                std::fprintf(
                    stderr,
                    "xrf: WARNING: a thread asked for %s priority %d, which this user may not have "
                    "(no CAP_SYS_NICE, RLIMIT_RTPRIO %ld): it runs without real-time scheduling, "
                    "without timing guarantees (docs/rt_core/runtime.md).\n",
                    policy == SCHED_FIFO ? "SCHED_FIFO" : "SCHED_RR", sp.sched_priority, [] {
                        rlimit rl{};
                        return getrlimit(RLIMIT_RTPRIO, &rl) == 0 ? (long)rl.rlim_cur : -1L;
                    }());
            }
        }
    }
    return r;
}
