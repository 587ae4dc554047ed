/*
 * evl_spidev.c — the ico board over the EVL out-of-band spidev interface (Raspberry Pi SPI0,
 * spi-bcm2835 with DMA). Built only with libevl (XRF_HAVE_EVL); spidev.c has the -ENOSYS stand-in.
 *
 * Open (in-band): the usual spidev set-up (mode 0, 8 bits, speed), then SPI_IOC_ENABLE_OOB_MODE
 * for 12-byte frames and mmap() of the DMA-coherent I/O area the core returns. Each xfer (from
 * the attached EVL loop thread): bit-reversed tx into iobuf + tx_offset, oob_ioctl(
 * SPI_IOC_RUN_OOB_XFER), bit-reversed rx out of iobuf + rx_offset — no in-band system call.
 */
#define _GNU_SOURCE

#include <errno.h>
#include <fcntl.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <unistd.h>

#include <linux/spi/spidev.h>
#include <evl/evl.h>
/* The out-of-band extension of spidev (kernel uapi); its name changed across EVL releases. */
#if __has_include(<evl/devices/spidev-abi.h>)
#include <evl/devices/spidev-abi.h>
#elif __has_include(<evl/devices/spidev.h>)
#include <evl/devices/spidev.h>
#elif __has_include(<uapi/evl/devices/spidev.h>)
#include <uapi/evl/devices/spidev.h>
#else
#error "no EVL spidev uapi header (evl/devices/spidev-abi.h or evl/devices/spidev.h)"
#endif

#include "xrf/ico.h"

struct evl_spidev_transport {
    struct xrf_ico_transport t; /* first, so the transport pointer is the object pointer */
    int fd;
    int oob_enabled;
    void *iobuf;
    size_t iobuf_len;
    volatile uint8_t *tx; /* iobuf + tx_offset (coherent DMA memory, uncached) */
    volatile uint8_t *rx; /* iobuf + rx_offset */
};

static int evl_spidev_xfer(struct xrf_ico_transport *t, const uint8_t tx[XRF_ICO_FRAME],
                           uint8_t rx[XRF_ICO_FRAME])
{
    struct evl_spidev_transport *s = (struct evl_spidev_transport *)t;
    /* The board shifts LSB-first and the bcm2835 controller only MSB-first. */
    for (int i = 0; i < XRF_ICO_FRAME; i++)
        s->tx[i] = xrf_ico_bitrev8(tx[i]);
    if (oob_ioctl(s->fd, SPI_IOC_RUN_OOB_XFER) != 0)
        return errno ? -errno : -EIO;
    for (int i = 0; i < XRF_ICO_FRAME; i++)
        rx[i] = xrf_ico_bitrev8(s->rx[i]);
    return 0;
}

static void evl_spidev_close(struct xrf_ico_transport *t)
{
    struct evl_spidev_transport *s = (struct evl_spidev_transport *)t;
    if (!s)
        return;
    if (s->iobuf && s->iobuf != MAP_FAILED)
        munmap(s->iobuf, s->iobuf_len);
    if (s->fd >= 0) {
        if (s->oob_enabled)
            ioctl(s->fd, SPI_IOC_DISABLE_OOB_MODE);
        close(s->fd);
    }
    free(s);
}

int xrf_evl_spidev_open(const char *device, uint32_t speed_hz, struct xrf_ico_transport **out)
{
    /* One board: the out-of-band transport has no per-board devices yet (a list is refused
     * rather than opened as one odd path). */
    if (device != NULL && strchr(device, ',') != NULL)
        return -EOPNOTSUPP;
    if (!device || !out || speed_hz == 0)
        return -EINVAL;
    *out = NULL;
    struct evl_spidev_transport *s = calloc(1, sizeof *s);
    if (!s)
        return -ENOMEM;
    s->iobuf = NULL;
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
        ioctl(s->fd, SPI_IOC_WR_MAX_SPEED_HZ, &speed_hz) < 0)
        goto fail;

    /* -ENODEV here usually means the controller has no DMA channel (needed for oob). */
    struct spi_ioc_oob_setup setup;
    memset(&setup, 0, sizeof setup);
    setup.frame_len = XRF_ICO_FRAME;
    setup.speed_hz = speed_hz;
    setup.bits_per_word = 8;
    if (ioctl(s->fd, SPI_IOC_ENABLE_OOB_MODE, &setup) < 0)
        goto fail;
    s->oob_enabled = 1;

    if (setup.iobuf_len == 0 || (size_t)setup.tx_offset + XRF_ICO_FRAME > setup.iobuf_len ||
        (size_t)setup.rx_offset + XRF_ICO_FRAME > setup.iobuf_len) {
        errno = EPROTO;
        goto fail;
    }
    s->iobuf_len = setup.iobuf_len;
    s->iobuf = mmap(NULL, s->iobuf_len, PROT_READ | PROT_WRITE, MAP_SHARED, s->fd, 0);
    if (s->iobuf == MAP_FAILED) {
        s->iobuf = NULL;
        goto fail;
    }
    s->tx = (volatile uint8_t *)s->iobuf + setup.tx_offset;
    s->rx = (volatile uint8_t *)s->iobuf + setup.rx_offset;
    for (int i = 0; i < XRF_ICO_FRAME; i++) {
        s->tx[i] = 0;
        s->rx[i] = 0;
    }

    s->t.name = "evl-spidev";
    s->t.xfer = evl_spidev_xfer;
    s->t.close = evl_spidev_close;
    *out = &s->t;
    return 0;

fail : {
    int err = errno ? -errno : -EIO;
    evl_spidev_close(&s->t);
    return err;
}
}
