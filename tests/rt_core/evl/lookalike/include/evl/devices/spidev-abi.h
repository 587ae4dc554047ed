/* EVL look-alike for CI, not the EVL kernel uapi (see evl/evl.h): the out-of-band extension of
 * spidev that src/evl_spidev.c compiles against. There is no such device on CI: opening
 * /dev/spidevX.Y fails before these ioctls are used. */
#ifndef XRF_EVL_LOOKALIKE_SPIDEV_ABI_H
#define XRF_EVL_LOOKALIKE_SPIDEV_ABI_H

#include <linux/ioctl.h>
#include <linux/spi/spidev.h>
#include <linux/types.h>

struct spi_ioc_oob_setup {
    /* in */
    __u32 frame_len;
    __u32 speed_hz;
    __u8 bits_per_word;
    /* out */
    __u32 iobuf_len;
    __u32 tx_offset;
    __u32 rx_offset;
};

#define SPI_IOC_ENABLE_OOB_MODE _IOW(SPI_IOC_MAGIC, 50, struct spi_ioc_oob_setup)
#define SPI_IOC_DISABLE_OOB_MODE _IO(SPI_IOC_MAGIC, 51)
#define SPI_IOC_RUN_OOB_XFER _IO(SPI_IOC_MAGIC, 52)

#endif
