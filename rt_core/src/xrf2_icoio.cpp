// IcoIo over the runtime's transport.
#include "IcoIo.hpp"

#include <cerrno>
#include <cstddef>
#include <cstring>

#include "xrf/ico.h"
#include "xrf/runtime.hpp"

// IcoRead is XRF2's layout of the ALL reply; it is xrf_ico_in's too, so the decoded reply is
// copied whole instead of field by field (checked here, where both are known).
static_assert(sizeof(IcoIo::IcoRead) == sizeof(xrf_ico_in) &&
                  offsetof(IcoIo::IcoRead, channel1) == offsetof(xrf_ico_in, enc) &&
                  offsetof(IcoIo::IcoRead, channel4) == offsetof(xrf_ico_in, enc[3]) &&
                  offsetof(IcoIo::IcoRead, channel1_1) == offsetof(xrf_ico_in, din) &&
                  offsetof(IcoIo::IcoRead, channel4_2) == offsetof(xrf_ico_in, din[7]) &&
                  sizeof(bool) == sizeof(uint8_t),
              "IcoIo::IcoRead must have xrf_ico_in's layout");

int IcoIo::xfer(const uint8_t *tx, uint8_t *rx)
{
    xrf_ico_transport *t = transport_;
    if (t == nullptr) {
        // Until the runtime has one (it reports a failed open once and keeps returning NULL).
        t = xrf::Runtime::instance().transport();
        if (t == nullptr)
            return -ENODEV;
        transport_ = t;
    }
    if (board_ == 0)
        return t->xfer(t, tx, rx);
    // Another board of the bench: only a transport that has it (-ENODEV otherwise: a bench of
    // one board reads as a missing board, as XRF2's IcoIo would see no answer).
    return t->xfer_board != nullptr ? t->xfer_board(t, board_, tx, rx) : -ENODEV;
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
    if (pwm_max_ < 0)
        pwm_max_ = xrf::Runtime::instance().pwmMax();
    xrf_ico_encode_pwm(channel, v, pwm_max_, tx);
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
    if (pwm_max_ < 0)
        pwm_max_ = xrf::Runtime::instance().pwmMax();
    uint8_t tx[XRF_ICO_FRAME], rx[XRF_ICO_FRAME];
    // last_pwm_: what the frame carries, the limit applied (pwm_max_ is 0..2047, its own
    // magnitude limit). Two calls rather than one on a chosen struct: inlined, each reads its
    // operands directly.
    const int32_t lim = xrf_ico_mag_limit(pwm_max_);
    if (outputs_enabled_) {
        const xrf_ico_out out = {{w.pwm1, w.pwm2, w.pwm3, w.pwm4},
                                 {w.val1, w.val2, w.val3, w.val4}};
        xrf_ico_encode_all_inline(&out, lim, tx, last_pwm_);
        std::memcpy(last_dout_, out.dout, sizeof last_dout_);
    } else {
        static const xrf_ico_out off = {{0, 0, 0, 0}, {0, 0, 0, 0}};
        xrf_ico_encode_all_inline(&off, lim, tx, last_pwm_);
        std::memset(last_dout_, 0, sizeof last_dout_);
    }
    // The transport's call directly once it is known (every cycle but the first): no second call.
    xrf_ico_transport *t = transport_;
    int r = t != nullptr && board_ == 0 ? t->xfer(t, tx, rx) : xfer(tx, rx);
    if (r != 0)
        return r;
    if (rd != nullptr) {
        xrf_ico_in in;
        xrf_ico_decode_all_inline(rx, &in);
        std::memcpy(static_cast<void *>(rd), &in, sizeof in);
    }
    return 0;
}
