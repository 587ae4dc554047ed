// IcoIo over the runtime's transport.
#include "IcoIo.hpp"

#include <cerrno>
#include <cstring>

#include "xrf/ico.h"
#include "xrf/runtime.hpp"

int IcoIo::xfer(const uint8_t *tx, uint8_t *rx)
{
    xrf_ico_transport *t = xrf::Runtime::instance().transport();
    if (t == nullptr)
        return -ENODEV;
    return t->xfer(t, tx, rx);
}

int IcoIo::init()
{
    uint8_t tx[XRF_ICO_FRAME], rx[XRF_ICO_FRAME];
    xrf_ico_frame_op(XRF_ICO_INIT, tx);
    int r = xfer(tx, rx);
    missing_ = r != 0 || rx[XRF_ICO_INIT_REPLY_BYTE] != XRF_ICO_INIT_REPLY;
    return missing_ ? -ENODEV : 0;
}

int IcoIo::reset()
{
    uint8_t tx[XRF_ICO_FRAME], rx[XRF_ICO_FRAME];
    xrf_ico_frame_op(XRF_ICO_RESET, tx);
    std::memset(last_pwm_, 0, sizeof last_pwm_);
    std::memset(last_dout_, 0, sizeof last_dout_);
    return xfer(tx, rx);
}

int IcoIo::test()
{
    uint8_t tx[XRF_ICO_FRAME], rx[XRF_ICO_FRAME];
    xrf_ico_test_pattern(tx);
    int r = xfer(tx, rx);
    if (r != 0)
        return r;
    return xrf_ico_test_bit_errors(rx) == 0 ? 0 : -EIO;
}

int IcoIo::setOutput(int channel, int16_t value, bool pin)
{
    if (channel < 1 || channel > 4)
        return -EINVAL;
    uint8_t tx[XRF_ICO_FRAME], rx[XRF_ICO_FRAME];
    const int16_t v = outputs_enabled_ ? value : 0;
    xrf_ico_encode_pwm(channel, v, xrf::Runtime::instance().pwmMax(), tx);
    // The digital output shares the channel's word (bit 15), as in the ALL frame.
    if (outputs_enabled_ && pin)
        tx[3] |= 0x80;
    last_pwm_[channel - 1] = v;
    last_dout_[channel - 1] = outputs_enabled_ && pin;
    return xfer(tx, rx);
}

IcoIo::ReadValue IcoIo::getInput(int channel)
{
    ReadValue v{0, 0, 0};
    if (channel < 1 || channel > 4)
        return v;
    uint8_t tx[XRF_ICO_FRAME], rx[XRF_ICO_FRAME];
    xrf_ico_frame_op((uint8_t)(XRF_ICO_ENC_1 + channel - 1), tx);
    if (xfer(tx, rx) != 0)
        return v;
    // The reply word as in the ALL frame: bits 0-13 encoder, bit 14 pin 1, bit 15 pin 2.
    const unsigned word = (unsigned)rx[1] | ((unsigned)rx[2] << 8);
    v.enc = (unsigned)xrf_ico_decode_enc(rx);
    v.pin1 = (word >> 14) & 1u;
    v.pin2 = (word >> 15) & 1u;
    return v;
}

int IcoIo::update_io(const IcoWrite &w, IcoRead *rd)
{
    xrf_ico_out out;
    if (outputs_enabled_) {
        out = {{w.pwm1, w.pwm2, w.pwm3, w.pwm4}, {w.val1, w.val2, w.val3, w.val4}};
    } else {
        std::memset(&out, 0, sizeof out);
    }
    const int16_t max = xrf::Runtime::instance().pwmMax();
    for (int i = 0; i < 4; i++) {
        int16_t p = out.pwm[i];
        last_pwm_[i] = p > max ? max : (p < -max ? (int16_t)-max : p);
        last_dout_[i] = out.dout[i] ? 1 : 0;
    }
    uint8_t tx[XRF_ICO_FRAME], rx[XRF_ICO_FRAME];
    xrf_ico_encode_all(&out, max, tx);
    int r = xfer(tx, rx);
    if (r != 0)
        return r;
    if (rd != nullptr) {
        xrf_ico_in in;
        xrf_ico_decode_all(rx, &in);
        rd->channel1 = in.enc[0];
        rd->channel2 = in.enc[1];
        rd->channel3 = in.enc[2];
        rd->channel4 = in.enc[3];
        rd->channel1_1 = in.din[0];
        rd->channel1_2 = in.din[1];
        rd->channel2_1 = in.din[2];
        rd->channel2_2 = in.din[3];
        rd->channel3_1 = in.din[4];
        rd->channel3_2 = in.din[5];
        rd->channel4_1 = in.din[6];
        rd->channel4_2 = in.din[7];
    }
    return 0;
}
