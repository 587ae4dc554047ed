// ICommunicationFullDuplex — XRF2's interface of a full-duplex channel (the SPI link to the board).
#pragma once

#include "ICommunication.h"

class ICommunicationFullDuplex : public ICommunication
{
public:
    virtual ~ICommunicationFullDuplex() {}
    // Sends data_size bytes of tx_data while receiving as many into rx_data.
    virtual int transfer(const void *tx_data, void *rx_data, int data_size) = 0;
};
