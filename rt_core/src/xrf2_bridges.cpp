// XRF2's bridge and SPI members of XenoFrtRosIco over XRF Lab's channels and transport
// (see XenoRosCommunication.hpp and XenoSpiControllerHandler.hpp for what each call means here).
#include "XenoRosCommunication.hpp"
#include "XenoSpiControllerHandler.hpp"

#include <cerrno>
#include <cstring>

#include "xrf/ico.h"
#include "xrf/runtime.hpp"

int XenoRosCommunication::read(void *rx_data, int data_size)
{
    if (rx_data == nullptr || data_size < 0)
        return -EINVAL;
    if (in_ == nullptr)
        return 0; // commands: the framework has applied this cycle's already
    const int n = data_size < in_size_ ? data_size : in_size_;
    std::memcpy(rx_data, in_, (size_t)n);
    return n;
}

int XenoRosCommunication::write(const void *tx_data, int data_size)
{
    if (tx_data == nullptr || data_size < 0)
        return -EINVAL;
    if (out_ == nullptr)
        return data_size; // the state: the framework publishes it every cycle
    const int n = data_size < out_size_ ? data_size : out_size_;
    std::memcpy(out_, tx_data, (size_t)n);
    return n;
}

int XenoSpiControllerHandler::transfer(const void *tx_data, void *rx_data, int data_size)
{
    if (tx_data == nullptr || rx_data == nullptr || data_size != XRF_ICO_FRAME)
        return -EINVAL;
    // Frames that drive outputs go through IcoIo (actuate_data, setOutput), where the PWM limit
    // and "no motion before initialise, in ERROR or after QUIT" apply; a raw frame must not
    // bypass them. Reading, INIT, RESET and TEST pass.
    const uint8_t op = static_cast<const uint8_t *>(tx_data)[0];
    if (op == XRF_ICO_ALL || (op >= XRF_ICO_PWM_1 && op <= XRF_ICO_PWM_1 + 3))
        return -EPERM;
    xrf_ico_transport *t = xrf::Runtime::instance().transport();
    if (t == nullptr)
        return -ENODEV;
    const int r =
        t->xfer(t, static_cast<const uint8_t *>(tx_data), static_cast<uint8_t *>(rx_data));
    return r != 0 ? r : data_size;
}

int XenoSpiControllerHandler::read(void *rx_data, int data_size)
{
    uint8_t noop[XRF_ICO_FRAME] = {0};
    return transfer(noop, rx_data, data_size);
}

int XenoSpiControllerHandler::write(const void *tx_data, int data_size)
{
    uint8_t reply[XRF_ICO_FRAME];
    return transfer(tx_data, reply, data_size);
}
