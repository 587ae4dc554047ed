// What a loop process does when it lacks the privileges an XRF2 main assumes (a normal user on a
// laptop or in CI: no RLIMIT_RTPRIO, a small RLIMIT_MEMLOCK, no CAP_IPC_LOCK/CAP_SYS_NICE). It
// runs anyway and says what it could not have, as the posix backend does for SCHED_FIFO.
#pragma once

#include <cstddef>

namespace xrf
{

// Bytes RLIMIT_MEMLOCK leaves for locking beyond what this process maps now; (size_t)-1 when
// locking is not limited (RLIM_INFINITY or CAP_IPC_LOCK).
size_t memlockHeadroom();
// The RLIMIT_MEMLOCK soft limit in bytes, (size_t)-1 when unlimited.
size_t memlockLimit();

// Before the loop maps its channels: if the memlock limit cannot hold what the loop will map
// (`need` bytes more), memory locking is switched off for the process (munlockall(): an
// MCL_FUTURE set by main or evl_init() would make every later mapping fail with EAGAIN) and
// a warning says so. Returns true when the loop may still lock its memory.
bool fitMemoryLocking(size_t need, bool quiet);

// The SCHED_FIFO/RR priority main asked for on a thread it could not have (pthread_create
// answered EPERM and the thread was started without it), 0 if none.
int refusedThreadPriority();

} // namespace xrf
