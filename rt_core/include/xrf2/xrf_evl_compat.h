// What XRF2's headers made visible to student code, transitively: the EVL calls a student main
// uses, error(), mlockall(), pthreads, <functional>, <string>. With libevl the real <evl/evl.h>;
// without it the runtime provides evl_init() and evl_printf() with the same meaning.
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

#ifdef XRF_HAVE_EVL
#include <evl/evl.h>
#else
extern "C" {
int evl_init(void);
// Goes to the monitor stream (never blocks the loop); printed by the process's helper thread.
int evl_printf(const char *fmt, ...) __attribute__((format(printf, 1, 2)));
}
#endif
