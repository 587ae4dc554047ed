/*
 * stall_probe.c — what a loop on CPU N sees of the machine, without the appliance: a thread at
 * SCHED_FIFO (below the loop's priority, so it never delays one) sleeping to a 1 ms absolute
 * grid with clock_nanosleep, as rt_core's posix backend does. A wake-up later than --stall-ms is
 * printed with its time, and, with --trace-instance, the ftrace instance of that name is stopped
 * at once so its buffer ends with the stall (hang_repro.py reads it: who ran on the CPU, whether
 * the timer interrupt came). Not a test: bench/safety/README.md.
 *
 *   stall_probe CPU PRIO STALL_MS SECONDS [TRACE_INSTANCE]
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <pthread.h>
#include <sched.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <time.h>
#include <unistd.h>

static int64_t mono_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

int main(int argc, char **argv)
{
    if (argc < 5) {
        fprintf(stderr, "usage: %s CPU PRIO STALL_MS SECONDS [TRACE_INSTANCE]\n", argv[0]);
        return 2;
    }
    int cpu = atoi(argv[1]), prio = atoi(argv[2]);
    int64_t stall_ns = (int64_t)atoi(argv[3]) * 1000000LL;
    int64_t seconds = atoll(argv[4]);
    int trace_fd = -1;
    if (argc > 5) {
        char path[256];
        snprintf(path, sizeof path, "/sys/kernel/tracing/instances/%s/tracing_on", argv[5]);
        trace_fd = open(path, O_WRONLY | O_CLOEXEC);
        if (trace_fd < 0)
            fprintf(stderr, "stall_probe: %s: %s\n", path, strerror(errno));
    }
    cpu_set_t set;
    CPU_ZERO(&set);
    CPU_SET(cpu, &set);
    if (sched_setaffinity(0, sizeof set, &set) != 0)
        perror("sched_setaffinity");
    mlockall(MCL_CURRENT | MCL_FUTURE);
    struct sched_param sp = {.sched_priority = prio};
    if (sched_setscheduler(0, SCHED_FIFO, &sp) != 0)
        perror("sched_setscheduler");
    const int64_t period = 1000000;
    int64_t t0 = mono_ns(), next = t0 + period, end = t0 + seconds * 1000000000LL;
    int64_t max = 0, stalls = 0, cycles = 0, over1 = 0;
    while (next < end) {
        struct timespec ts = {(time_t)(next / 1000000000LL), (long)(next % 1000000000LL)};
        while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL) == EINTR) {}
        int64_t now = mono_ns(), late = now - next;
        cycles++;
        if (late > max)
            max = late;
        if (late > period)
            over1++;
        if (late > stall_ns) {
            if (trace_fd >= 0 && write(trace_fd, "0", 1) != 1)
                perror("tracing_on");
            struct timespec rt;
            clock_gettime(CLOCK_REALTIME, &rt);
            stalls++;
            printf("STALL cpu %d late %.3f ms at mono %.6f s (deadline %.6f) utc %ld.%03ld\n", cpu,
                   late / 1e6, now / 1e9, next / 1e9, (long)rt.tv_sec, rt.tv_nsec / 1000000);
            fflush(stdout);
            trace_fd = trace_fd >= 0 ? (close(trace_fd), -1) : -1; /* once: the buffer is kept */
        }
        next += period;
        if (next <= now) /* overrun: on to the first deadline ahead, as the loop does */
            next += ((now - next) / period + 1) * period;
    }
    printf("END cpu %d cycles %lld max %.3f ms >1ms %lld stalls>%lldms %lld\n", cpu,
           (long long)cycles, max / 1e6, (long long)over1, (long long)(stall_ns / 1000000),
           (long long)stalls);
    return 0;
}
