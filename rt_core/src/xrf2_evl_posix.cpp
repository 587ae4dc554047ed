// The libevl calls XRF2 student code makes, for builds without libevl (see
// include/evl_posix/evl/evl.h for what is covered and what each means here). evl_init and
// evl_printf live in runtime.cpp. None of these runs in the loop's per-cycle path unless the
// student's hook calls it, as with libevl.
#include "xrf2_compat.hpp"

#ifdef XRF_HAVE_EVL

void xrf2::markLoopThreadAttached() {}

#else

#include <cerrno>
#include <cstdarg>
#include <pthread.h>
#include <sched.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <evl/evl.h>

#include "xrf/runtime.hpp"

namespace
{

// The caller's descriptor once attached (its kernel thread id: unique, positive), else -1.
thread_local int self_efd = -1;

int attachCaller()
{
    if (self_efd < 0)
        self_efd = (int)syscall(SYS_gettid);
    return self_efd;
}

} // namespace

void xrf2::markLoopThreadAttached()
{
    attachCaller();
}

extern "C" {

int evl_attach_thread(int flags, const char *fmt, ...)
{
    (void)flags;
    (void)fmt; // the name matters to libevl's /dev/evl/thread/<name>; nothing to name here
    return attachCaller();
}

int evl_attach_self(const char *fmt, ...)
{
    (void)fmt;
    return attachCaller();
}

int evl_detach_self(void)
{
    if (self_efd < 0)
        return -EPERM;
    self_efd = -1;
    return 0;
}

int evl_get_self(void)
{
    return self_efd >= 0 ? self_efd : -EPERM;
}

int evl_switch_oob(void)
{
    return self_efd >= 0 ? 0 : -EPERM;
}

int evl_switch_inband(void)
{
    return 0;
}

bool evl_is_inband(void)
{
    return true;
}

static int callerOnly(int efd)
{
    // 0 and the caller's own descriptor name the caller; other threads are not reachable here.
    if (efd == 0 || (self_efd >= 0 && efd == self_efd))
        return 0;
    return -ESRCH;
}

int evl_set_schedattr(int efd, const struct evl_sched_attrs *attrs)
{
    if (attrs == nullptr)
        return -EINVAL;
    int r = callerOnly(efd);
    if (r != 0)
        return r;
    const int policy = attrs->sched_policy;
    if (policy != SCHED_FIFO && policy != SCHED_RR && policy != SCHED_OTHER)
        return -EINVAL;
    sched_param p{};
    p.sched_priority = policy == SCHED_OTHER ? 0 : attrs->sched_priority;
    return -pthread_setschedparam(pthread_self(), policy, &p);
}

int evl_get_schedattr(int efd, struct evl_sched_attrs *attrs)
{
    if (attrs == nullptr)
        return -EINVAL;
    int r = callerOnly(efd);
    if (r != 0)
        return r;
    int policy = 0;
    sched_param p{};
    r = pthread_getschedparam(pthread_self(), &policy, &p);
    if (r != 0)
        return -r;
    attrs->sched_policy = policy;
    attrs->sched_priority = p.sched_priority;
    return 0;
}

int evl_yield(void)
{
    return sched_yield() == 0 ? 0 : -errno;
}

int evl_vprintf(const char *fmt, va_list ap)
{
    xrf::Runtime::instance().monitorWrite(fmt, ap);
    return 0;
}

} // extern "C"

#endif
