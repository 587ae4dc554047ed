/* EVL look-alike for CI, not libevl (see evl/evl.h): proxies and evl_printf. */
#ifndef XRF_EVL_LOOKALIKE_PROXY_H
#define XRF_EVL_LOOKALIKE_PROXY_H

#include <stdarg.h>
#include <stddef.h>

#include <evl/factory.h>

#ifdef __cplusplus
extern "C" {
#endif

/* A proxy relays what an out-of-band thread oob_write()s to an in-band file (here: at once). */
int evl_create_proxy(int targetfd, size_t bufsz, size_t granularity, int flags, const char *fmt, ...)
    __attribute__((format(printf, 5, 6)));
#define evl_new_proxy(__fd, __bufsz, __fmt, ...) \
    evl_create_proxy(__fd, __bufsz, 0, EVL_CLONE_PRIVATE, __fmt, ##__VA_ARGS__)

/* Formatted output to stdout through a built-in proxy: no switch to in-band. */
int evl_printf(const char *fmt, ...) __attribute__((format(printf, 1, 2)));
int evl_vprintf(const char *fmt, va_list ap);

#ifdef __cplusplus
}
#endif

#endif
