// What XRF2's headers made visible to student code, transitively: libevl (<evl/evl.h> and its
// thread/clock/proxy parts), error(), mlockall(), pthreads, <functional>, <string>. With libevl
// (XRF_HAVE_EVL) the real <evl/evl.h>; without it rt_core's POSIX equivalent of the same calls
// (include/evl_posix/evl/evl.h, on the include path only in such builds).
#pragma once

#include <cerrno>
#include <cstdint>
#include <error.h>
#include <functional>
#include <pthread.h>
#include <sched.h>
#include <string>
#include <sys/mman.h>
#include <sys/types.h>
#include <unistd.h>

#include <evl/evl.h>
#include <evl/thread.h>
#include <evl/clock.h>
#include <evl/proxy.h>
