/* EVL look-alike for CI, not libevl (see evl/evl.h): the out-of-band I/O calls.
 * They return -1 and set errno, as libevl's do (unlike the evl_* calls). */
#ifndef XRF_EVL_LOOKALIKE_SYSCALL_H
#define XRF_EVL_LOOKALIKE_SYSCALL_H

#include <sys/types.h>

#ifdef __cplusplus
extern "C" {
#endif

ssize_t oob_read(int efd, void *buf, size_t count);
ssize_t oob_write(int efd, const void *buf, size_t count);
int oob_ioctl(int efd, unsigned long request, ...);

#ifdef __cplusplus
}
#endif

#endif
