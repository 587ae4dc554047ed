/*
 * spidev.c — the ico board over Linux spidev (in-band). Also the -ENOSYS stand-in for the EVL
 * out-of-band transport in builds without libevl (the real one is evl_spidev.c).
 */
#define _POSIX_C_SOURCE 200809L

#include <errno.h>
#include <fcntl.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ioctl.h>
#include <unistd.h>

#include <linux/spi/spidev.h>

#include "xrf/ico.h"

struct spidev_transport {
    struct xrf_ico_transport t; /* first, so the transport pointer is the object pointer */
    int fd;
    struct spi_ioc_transfer xfer;
    uint8_t tx[XRF_ICO_FRAME];
    uint8_t rx[XRF_ICO_FRAME];
};

static int spidev_xfer(struct xrf_ico_transport *t, const uint8_t tx[XRF_ICO_FRAME],
                       uint8_t rx[XRF_ICO_FRAME])
{
    struct spidev_transport *s = (struct spidev_transport *)t;
    /* The board shifts LSB-first and the bcm2835 controller only MSB-first. */
    for (int i = 0; i < XRF_ICO_FRAME; i++)
        s->tx[i] = xrf_ico_bitrev8(tx[i]);
    if (ioctl(s->fd, SPI_IOC_MESSAGE(1), &s->xfer) < 0)
        return -errno;
    for (int i = 0; i < XRF_ICO_FRAME; i++)
        rx[i] = xrf_ico_bitrev8(s->rx[i]);
    return 0;
}

static void spidev_close(struct xrf_ico_transport *t)
{
    struct spidev_transport *s = (struct spidev_transport *)t;
    if (!s)
        return;
    if (s->fd >= 0)
        close(s->fd);
    free(s);
}

int xrf_spidev_open(const char *device, uint32_t speed_hz, struct xrf_ico_transport **out)
{
    if (!device || !out || speed_hz == 0)
        return -EINVAL;
    *out = NULL;
    struct spidev_transport *s = calloc(1, sizeof *s);
    if (!s)
        return -ENOMEM;
    s->fd = open(device, O_RDWR | O_CLOEXEC);
    if (s->fd < 0) {
        int err = -errno;
        free(s);
        return err;
    }
    uint8_t mode = SPI_MODE_0;
    uint8_t bits = 8;
    if (ioctl(s->fd, SPI_IOC_WR_MODE, &mode) < 0 ||
        ioctl(s->fd, SPI_IOC_WR_BITS_PER_WORD, &bits) < 0 ||
        ioctl(s->fd, SPI_IOC_WR_MAX_SPEED_HZ, &speed_hz) < 0) {
        int err = -errno;
        spidev_close(&s->t);
        return err;
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
    *out = &s->t;
    return 0;
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
