// XenoSpiControllerHandler — XRF2's SPI link to the ico board (XenoFrtRosIco::spi_controller).
// Here it is a view of the transport the runtime opened (EVL out-of-band spidev, Linux spidev or
// the simulated board): transfer() exchanges one frame with the board, as XRF2's did.
#pragma once

#include <cstdio>
#include <errno.h>
#include <error.h>
#include <fcntl.h>
#include <stdint.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <sys/sysinfo.h>
#include <sys/types.h>
#include <time.h>
#include <unistd.h>
#if __has_include(<linux/spi/spidev.h>)
#include <linux/spi/spidev.h>
#endif

#include "ICommunicationFullDuplex.h"
#include "configuration.h"
#include "debug_settings.h"
#include "xrf_evl_compat.h"

#ifndef MILLION
#define MILLION 1000000L
#endif
#ifndef BILLION
#define BILLION 1000000000L
#endif

class XenoSpiControllerHandler : public ICommunicationFullDuplex
{
public:
    XenoSpiControllerHandler() = default;
    // XRF2's constructor (LSB-first flag, frame length, clock): the runtime's transport decides
    // these (XRF_SPI_DEVICE, XRF_SPI_SPEED; frames are always 12 bytes, LSB first on the wire).
    XenoSpiControllerHandler(uint8_t lsb, int data_length, uint32_t speed)
    {
        (void)lsb;
        (void)data_length;
        (void)speed;
    }
    void open() override {}
    void close() override {}
    // A frame is always a full exchange: read() sends NOOP, write() discards the reply.
    int read(void *rx_data, int data_size) override;
    int write(const void *tx_data, int data_size) override;
    // One 12-byte frame (FRAME_SIZE): data_size must be 12. Returns 12, or a negative errno;
    // -EPERM for ALL and PWM_n frames (outputs go through ico_io / actuate_data, where the PWM
    // limit and the safety states apply).
    int transfer(const void *tx_data, void *rx_data, int data_size) override;
};
