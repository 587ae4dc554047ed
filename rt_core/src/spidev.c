/*
 * spidev.c — the ico boards over Linux spidev (in-band), one device per board. Also the -ENOSYS stand-in for the EVL
 * out-of-band transport in builds without libevl (the real one is evl_spidev.c).
 */
#define _POSIX_C_SOURCE 200809L

#include <errno.h>
#include <fcntl.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <linux/spi/spidev.h>

#include "xrf/channels.h"
#include "xrf/ico.h"

/* One device per ico board (channels.h: board b carries channels 4b+1 .. 4b+4; on the Pi each
 * board on a chip select of its own, docs/install/pi.md). One transfer description, retargeted
 * by the descriptor the ioctl goes to: the buffers and speed are the same for every board. */
struct spidev_transport {
    struct xrf_ico_transport t; /* first, so the transport pointer is the object pointer */
    int fd[XRF_MAX_BOARDS];
    struct spi_ioc_transfer xfer;
    uint8_t tx[XRF_ICO_FRAME];
    uint8_t rx[XRF_ICO_FRAME];
};

static int spidev_xfer_fd(struct spidev_transport *s, int fd, const uint8_t tx[XRF_ICO_FRAME],
                          uint8_t rx[XRF_ICO_FRAME])
{
    /* The board shifts LSB-first and the bcm2835 controller only MSB-first. */
    for (int i = 0; i < XRF_ICO_FRAME; i++)
        s->tx[i] = xrf_ico_bitrev8(tx[i]);
    if (ioctl(fd, SPI_IOC_MESSAGE(1), &s->xfer) < 0)
        return -errno;
    for (int i = 0; i < XRF_ICO_FRAME; i++)
        rx[i] = xrf_ico_bitrev8(s->rx[i]);
    return 0;
}

static int spidev_xfer(struct xrf_ico_transport *t, const uint8_t tx[XRF_ICO_FRAME],
                       uint8_t rx[XRF_ICO_FRAME])
{
    struct spidev_transport *s = (struct spidev_transport *)t;
    return spidev_xfer_fd(s, s->fd[0], tx, rx);
}

static int spidev_xfer_board(struct xrf_ico_transport *t, int board,
                             const uint8_t tx[XRF_ICO_FRAME], uint8_t rx[XRF_ICO_FRAME])
{
    struct spidev_transport *s = (struct spidev_transport *)t;
    if (board < 0 || board >= t->boards)
        return -EINVAL;
    return spidev_xfer_fd(s, s->fd[board], tx, rx);
}

static void spidev_close(struct xrf_ico_transport *t)
{
    struct spidev_transport *s = (struct spidev_transport *)t;
    if (!s)
        return;
    for (int b = 0; b < XRF_MAX_BOARDS; b++)
        if (s->fd[b] >= 0)
            close(s->fd[b]);
    free(s);
}

/* One board's device, opened and set up (mode 0, 8 bits, speed): the descriptor or -errno. A
 * path that is no character device is -ENOTTY here, before any ioctl is tried on it. */
static int spidev_open_one(const char *path, uint32_t speed_hz)
{
    int fd = open(path, O_RDWR | O_CLOEXEC);
    if (fd < 0)
        return -errno; /* -ENOENT missing, -EISDIR a folder, -EACCES not ours */
    struct stat st;
    if (fstat(fd, &st) != 0 || !S_ISCHR(st.st_mode)) {
        close(fd);
        return -ENOTTY;
    }
    uint8_t mode = SPI_MODE_0;
    uint8_t bits = 8;
    if (ioctl(fd, SPI_IOC_WR_MODE, &mode) < 0 || ioctl(fd, SPI_IOC_WR_BITS_PER_WORD, &bits) < 0 ||
        ioctl(fd, SPI_IOC_WR_MAX_SPEED_HZ, &speed_hz) < 0) {
        int err = -errno;
        close(fd);
        return err;
    }
    return fd;
}

int xrf_spidev_open_bench(const char *devices, uint32_t speed_hz, struct xrf_ico_transport **out,
                          int *failed)
{
    if (failed)
        *failed = -1;
    if (!devices || !out || speed_hz == 0)
        return -EINVAL;
    *out = NULL;
    struct spidev_transport *s = calloc(1, sizeof *s);
    if (!s)
        return -ENOMEM;
    for (int b = 0; b < XRF_MAX_BOARDS; b++)
        s->fd[b] = -1;
    int boards = 0;
    const char *p = devices;
    for (;;) {
        const char *comma = strchr(p, ',');
        size_t len = comma ? (size_t)(comma - p) : strlen(p);
        char path[XRF_SPI_PATH_MAX];
        int r = 0;
        if (boards == XRF_MAX_BOARDS)
            r = -E2BIG; /* more devices than a bench has boards */
        else if (len == 0 || len >= sizeof path)
            r = -EINVAL;
        if (r == 0) {
            memcpy(path, p, len);
            path[len] = '\0';
            r = spidev_open_one(path, speed_hz);
        }
        if (r < 0) {
            if (failed)
                *failed = boards;
            spidev_close(&s->t);
            return r;
        }
        s->fd[boards++] = r;
        if (!comma)
            break;
        p = comma + 1;
    }
    /* Everything the transfer needs is fixed here, so xfer is two copies and one ioctl. */
    s->xfer.tx_buf = (uint64_t)(uintptr_t)s->tx;
    s->xfer.rx_buf = (uint64_t)(uintptr_t)s->rx;
    s->xfer.len = XRF_ICO_FRAME;
    s->xfer.speed_hz = speed_hz;
    s->xfer.bits_per_word = 8;
    s->xfer.delay_usecs = 0;
    s->xfer.cs_change = 0;
    s->t.name = "spidev";
    s->t.xfer = spidev_xfer;
    s->t.close = spidev_close;
    s->t.boards = boards;
    s->t.xfer_board = spidev_xfer_board;
    *out = &s->t;
    return 0;
}

int xrf_spidev_open(const char *devices, uint32_t speed_hz, struct xrf_ico_transport **out)
{
    return xrf_spidev_open_bench(devices, speed_hz, out, NULL);
}

#ifndef XRF_HAVE_EVL
int xrf_evl_spidev_open(const char *device, uint32_t speed_hz, struct xrf_ico_transport **out)
{
    (void)device;
    (void)speed_hz;
    if (out)
        *out = NULL;
    return -ENOSYS;
}
#endif
