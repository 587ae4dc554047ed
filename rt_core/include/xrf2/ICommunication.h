// ICommunication — XRF2's byte-channel interface (its cross-buffers, SPI and log file implemented
// it). Kept because the types of XenoFrtRosIco's bridge members derive from it and student code
// may hold them by this interface.
#pragma once

#include <cstdio>
#include <error.h>
#include <fcntl.h>
#include <stdint.h>
#include <string.h>
#include <unistd.h>

class ICommunication
{
public:
    virtual ~ICommunication() {}
    virtual void open() = 0;
    virtual void close() = 0;
    // Bytes read / written, or a negative errno.
    virtual int read(void *rx_data, int data_size) = 0;
    virtual int write(const void *tx_data, int data_size) = 0;
};
