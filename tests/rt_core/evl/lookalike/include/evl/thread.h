/* EVL look-alike for CI, not libevl (see evl/evl.h): attaching threads, mode bits, SIGDEBUG. */
#ifndef XRF_EVL_LOOKALIKE_THREAD_H
#define XRF_EVL_LOOKALIKE_THREAD_H

#include <signal.h>
#include <stdbool.h>

#include <evl/factory.h>
#include <evl/sched.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Thread mode bits for evl_set_thread_mode / evl_clear_thread_mode. */
#define EVL_T_WOSS 0x00000001  /* warn on stage switch: SIGDEBUG at every switch to in-band */
#define EVL_T_WOLI 0x00000002  /* warn on locking inconsistency (not emulated) */
#define EVL_T_HMSIG 0x00000004 /* report health-monitoring events by SIGDEBUG */

/* The signal the core sends to report a switch to in-band (with EVL_T_WOSS). */
#ifndef SIGDEBUG
#define SIGDEBUG SIGXCPU
#endif

int evl_attach_thread(int flags, const char *fmt, ...) __attribute__((format(printf, 2, 3)));
#define evl_attach_self(__fmt, ...) evl_attach_thread(EVL_CLONE_PRIVATE, __fmt, ##__VA_ARGS__)
int evl_detach_self(void);
int evl_get_self(void);
int evl_switch_oob(void);
int evl_switch_inband(void);
bool evl_is_inband(void);
int evl_set_thread_mode(int efd, int mask, int *oldmask);
int evl_clear_thread_mode(int efd, int mask, int *oldmask);

#ifdef __cplusplus
}
#endif

#endif
