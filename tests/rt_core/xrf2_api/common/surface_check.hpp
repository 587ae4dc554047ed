// A failed CHECK prints where and counts; main() prints "surface: N failed" at the end.
#pragma once

#include <cstdio>
#include <ctime>

extern int surface_failures;

#define CHECK(cond)                                                                                \
    do {                                                                                           \
        if (!(cond)) {                                                                             \
            surface_failures++;                                                                    \
            std::fprintf(stderr, "surface: FAIL %s:%d: %s\n", __FILE__, __LINE__, #cond);          \
        }                                                                                          \
    } while (0)

inline long long ns(const struct timespec &t)
{
    return (long long)t.tv_sec * 1000000000LL + t.tv_nsec;
}

int run_surface_loop();  // the release's XenoFrtRosIco controller (v1_0/ or v1_1/)
int check_headers();     // common/surface_headers.cpp
int check_evl();         // common/surface_evl.cpp
int check_types();       // common/surface_types.cpp
