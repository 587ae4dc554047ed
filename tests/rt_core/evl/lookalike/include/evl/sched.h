/* EVL look-alike for CI, not libevl (see evl/evl.h): scheduling attributes. */
#ifndef XRF_EVL_LOOKALIKE_SCHED_H
#define XRF_EVL_LOOKALIKE_SCHED_H

#include <sched.h>

#ifdef __cplusplus
extern "C" {
#endif

/* The policy an attached thread without SCHED_FIFO/RR gets on EVL. */
#ifndef SCHED_WEAK
#define SCHED_WEAK 43
#endif

struct evl_sched_attrs {
    int sched_policy;
    int sched_priority;
    int reserved[6]; /* policy-specific parameters (quota, TP) the backend does not use */
};

int evl_set_schedattr(int efd, const struct evl_sched_attrs *attrs);
int evl_get_schedattr(int efd, struct evl_sched_attrs *attrs);
int evl_yield(void);

#ifdef __cplusplus
}
#endif

#endif
