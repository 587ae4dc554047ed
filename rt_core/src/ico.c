/*
 * ico.c — frame builders and parsers for the ico-board FPGA protocol (XRF2_API.md, "IcoIo";
 * docs/rt_core/ico-protocol.md). Pure functions: the transports and the simulated board share
 * them, so there is one place that knows where each bit lives.
 */
#include <math.h>
#include <string.h>

#include "xrf/ico.h"

/* The TEST payload (bytes 1..11). Walking ones catch a stuck or swapped data line and a
 * one-bit shift of the frame; 0x35/0xCA are complementary and not bit-palindromes, so a
 * transport that forgets the LSB-first reversal cannot pass; 0x0F catches nibble swaps. */
static const uint8_t test_payload[XRF_ICO_FRAME - 1] = {
    0x01, 0x02, 0x04, 0x08, 0x10, 0x20, 0x40, 0x80, 0x35, 0xCA, 0x0F,
};

int16_t xrf_ico_pwm_max(double limit_fraction)
{
    /* NaN compares false everywhere: treat it as "no output" rather than full scale. */
    if (!(limit_fraction > 0.0))
        return 0;
    if (limit_fraction >= 1.0)
        return XRF_ICO_PWM_FULL;
    return (int16_t)floor(limit_fraction * XRF_ICO_PWM_FULL);
}

void xrf_ico_frame_op(uint8_t op, uint8_t frame[XRF_ICO_FRAME])
{
    memset(frame, 0, XRF_ICO_FRAME);
    frame[0] = op;
}

static void put_le16(uint8_t *p, uint16_t w)
{
    p[0] = (uint8_t)(w & 0xFF);
    p[1] = (uint8_t)(w >> 8);
}

static uint16_t get_le16(const uint8_t *p)
{
    return (uint16_t)(p[0] | (p[1] << 8));
}

void xrf_ico_encode_all(const struct xrf_ico_out *out, int16_t pwm_max,
                        uint8_t frame[XRF_ICO_FRAME])
{
    int16_t sent[4];
    xrf_ico_encode_all_inline(out, xrf_ico_mag_limit(pwm_max), frame, sent);
}

void xrf_ico_decode_all(const uint8_t reply[XRF_ICO_FRAME], struct xrf_ico_in *in)
{
    xrf_ico_decode_all_inline(reply, in);
}

void xrf_ico_encode_pwm(int channel, int16_t pwm, int16_t pwm_max, uint8_t frame[XRF_ICO_FRAME])
{
    /* A bad channel must not turn into some other opcode on the wire: send a NOOP instead. */
    if (channel < 1 || channel > 4) {
        xrf_ico_frame_op(XRF_ICO_NOOP, frame);
        return;
    }
    xrf_ico_frame_op((uint8_t)(XRF_ICO_PWM_1 + channel - 1), frame);
    /* The word is the channel's whole ALL word, digital output included; this builder has no
     * output argument, so bit 15 goes out as 0 (off) and a caller that wants the output on
     * sets it in byte 3 (0x80), as IcoIo::setOutput does. */
    put_le16(&frame[2], xrf_ico_out_word(pwm, 0, xrf_ico_mag_limit(pwm_max)));
}

int32_t xrf_ico_decode_enc(const uint8_t reply[XRF_ICO_FRAME])
{
    return (int32_t)(get_le16(&reply[1]) & XRF_ICO_WORD_MAG_MASK);
}

void xrf_ico_test_pattern(uint8_t frame[XRF_ICO_FRAME])
{
    frame[0] = XRF_ICO_TEST;
    memcpy(&frame[1], test_payload, sizeof test_payload);
}

int xrf_ico_test_bit_errors(const uint8_t reply[XRF_ICO_FRAME])
{
    /* Byte 0 is shifted out before the board has seen the opcode, so it carries nothing. */
    int errors = 0;
    for (size_t i = 0; i < sizeof test_payload; i++)
        errors += __builtin_popcount((unsigned)(reply[1 + i] ^ test_payload[i]));
    return errors;
}

uint8_t xrf_ico_bitrev8(uint8_t b)
{
    b = (uint8_t)(((b & 0xF0u) >> 4) | ((b & 0x0Fu) << 4));
    b = (uint8_t)(((b & 0xCCu) >> 2) | ((b & 0x33u) << 2));
    b = (uint8_t)(((b & 0xAAu) >> 1) | ((b & 0x55u) << 1));
    return b;
}
