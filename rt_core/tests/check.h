/*
 * check.h — the one check macro of rt_core's C unit tests (test_hold, test_ico_frames,
 * test_sim_board). A test file defines CHECK_NAME before including it.
 *
 * CHECK stops at the first failure: later checks often build on earlier ones, and a plant test
 * run on from a wrong state prints pages of consequences. check_summary() ends main().
 */
#ifndef XRF_TESTS_CHECK_H
#define XRF_TESTS_CHECK_H

#include <stdio.h>
#include <stdlib.h>

#ifndef CHECK_NAME
#error "define CHECK_NAME (the test's name in its summary line) before including check.h"
#endif

static int passed, failed;

static inline int check_summary(void)
{
    printf("%s: %d passed, %d failed\n", CHECK_NAME, passed, failed);
    return failed != 0;
}

#define CHECK(cond)                                                                  \
    do {                                                                             \
        if (cond) {                                                                  \
            passed++;                                                                \
        } else {                                                                     \
            failed++;                                                                \
            fprintf(stderr, "%s:%d: check failed: %s\n", __FILE__, __LINE__, #cond); \
            exit(check_summary());                                                   \
        }                                                                            \
    } while (0)

/* For plumbing inside helpers: fails like CHECK but is not counted as a check. */
#define MUST(cond)                                                               \
    do {                                                                         \
        if (!(cond)) {                                                           \
            fprintf(stderr, "%s:%d: required: %s\n", __FILE__, __LINE__, #cond); \
            failed++;                                                            \
            exit(check_summary());                                               \
        }                                                                        \
    } while (0)

#endif
