// The libevl calls XRF2 student code makes (the real libevl with XRF_HAVE_EVL, rt_core's POSIX
// equivalent otherwise), on a thread of its own as a student main would.
#include "XenoFrtRosIco.hpp"

#include "surface_check.hpp"

static void *evl_thread(void *)
{
    CHECK(evl_get_self() < 0); // not attached yet
    int efd = evl_attach_self("surface-%d", 1);
    CHECK(efd >= 0);
    CHECK(evl_get_self() == efd);
    struct evl_sched_attrs attrs;
    CHECK(evl_get_schedattr(efd, &attrs) == 0);
    CHECK(evl_set_schedattr(efd, &attrs) == 0); // its own policy and priority, set back
    struct timespec t0, t1, res;
    CHECK(evl_read_clock(EVL_CLOCK_MONOTONIC, &t0) == 0);
    CHECK(evl_read_clock(EVL_CLOCK_REALTIME, &t1) == 0);
    CHECK(evl_get_clock_resolution(EVL_CLOCK_MONOTONIC, &res) == 0);
    CHECK(evl_usleep(1000) == 0);
    CHECK(evl_read_clock(EVL_CLOCK_MONOTONIC, &t1) == 0);
    CHECK(ns(t1) - ns(t0) >= 1000000LL);
    struct timespec until = t1;
    until.tv_nsec += 1000000;
    if (until.tv_nsec >= SEC) {
        until.tv_nsec -= SEC;
        until.tv_sec++;
    }
    CHECK(evl_sleep_until(EVL_CLOCK_MONOTONIC, &until) == 0);
    CHECK(evl_read_clock(EVL_CLOCK_MONOTONIC, &t1) == 0 && ns(t1) >= ns(until));
    CHECK(evl_udelay(10) == 0);
    CHECK(evl_yield() == 0);
    CHECK(evl_switch_oob() == 0);
    CHECK(evl_switch_inband() == 0);
    (void)evl_is_inband();
    CHECK(evl_printf("surface: evl_printf %d\n", 1) >= 0);
    CHECK(evl_detach_self() == 0);
    CHECK(evl_get_self() < 0);
    return nullptr;
}

int check_evl()
{
    pthread_t th;
    CHECK(pthread_create(&th, nullptr, evl_thread, nullptr) == 0);
    pthread_join(th, nullptr);
    return 0;
}
