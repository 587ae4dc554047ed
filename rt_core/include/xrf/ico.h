/*
 * xrf/ico.h — the ico-board FPGA protocol (12-byte full-duplex frames, XRF2_API.md) and the
 * transport interface every way of reaching a board implements (Linux spidev, EVL out-of-band
 * spidev, the simulated board).
 *
 * Frames here are logical: byte 0 is the opcode. The wire is LSB-first; transports that talk to
 * real hardware bit-reverse each byte (the bcm2835 SPI controller cannot shift LSB-first).
 */
#ifndef XRF_ICO_H
#define XRF_ICO_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define XRF_ICO_FRAME 12

#define XRF_ICO_NOOP 0
#define XRF_ICO_INIT 1
#define XRF_ICO_RESET 2
#define XRF_ICO_ALL 3
#define XRF_ICO_PWM_1 4 /* ..PWM_4 = 7 */
#define XRF_ICO_ENC_1 8 /* ..ENC_4 = 11 */
#define XRF_ICO_TEST 12

#define XRF_ICO_INIT_REPLY_BYTE 4
#define XRF_ICO_INIT_REPLY 11
#define XRF_ICO_PWM_FULL 2047
#define XRF_ICO_ENC_MODULO 16384
#define XRF_ICO_DEFAULT_PWM_LIMIT 0.2 /* XRF2's MAX_PWM_OUTPUT */

/* What the loop wants on the board's outputs / what it read from its inputs. */
struct xrf_ico_out {
    int16_t pwm[4];  /* signed duty, full scale +-2047 */
    uint8_t dout[4]; /* digital output per channel */
};

struct xrf_ico_in {
    int32_t enc[4]; /* 14-bit unsigned counter, 0..16383 */
    uint8_t din[8]; /* channel1 pin1, channel1 pin2, ..., channel4 pin2 */
};

/* Largest |pwm| allowed for a limit given as a fraction of full scale (0.2 -> 409). */
int16_t xrf_ico_pwm_max(double limit_fraction);

/* Frame builders and parsers (pure functions, no I/O). */
void xrf_ico_frame_op(uint8_t op, uint8_t frame[XRF_ICO_FRAME]);
void xrf_ico_encode_all(const struct xrf_ico_out *out, int16_t pwm_max,
                        uint8_t frame[XRF_ICO_FRAME]);
void xrf_ico_decode_all(const uint8_t reply[XRF_ICO_FRAME], struct xrf_ico_in *in);
void xrf_ico_encode_pwm(int channel /* 1..4 */, int16_t pwm, int16_t pwm_max,
                        uint8_t frame[XRF_ICO_FRAME]);
int32_t xrf_ico_decode_enc(const uint8_t reply[XRF_ICO_FRAME]);
/* The TEST frame's echo pattern and its check: returns the number of wrong bits (0 = intact). */
void xrf_ico_test_pattern(uint8_t frame[XRF_ICO_FRAME]);
int xrf_ico_test_bit_errors(const uint8_t reply[XRF_ICO_FRAME]);
uint8_t xrf_ico_bitrev8(uint8_t b);

/* The ALL frame's words, defined once here and inline: IcoIo::update_io builds and parses an
 * ALL frame every cycle (as calls these were a quarter of the loop's framework instructions,
 * issue 30); xrf_ico_encode_all/xrf_ico_decode_all are the same code for everyone else. A
 * channel's word: bits 0-13 magnitude, bit 14 direction (1 = pwm >= 0), bit 15 digital output;
 * on the reply bits 0-13 are the encoder, 14 and 15 the channel's two input pins. */
#define XRF_ICO_WORD_MAG_MASK 0x3FFFu
#define XRF_ICO_WORD_DIR_BIT 0x4000u
#define XRF_ICO_WORD_DOUT_BIT 0x8000u

/* The largest magnitude a word may carry for a pwm_max (clamped to 0..XRF_ICO_WORD_MAG_MASK). */
static inline int32_t xrf_ico_mag_limit(int16_t pwm_max)
{
    int32_t lim = pwm_max < 0 ? 0 : pwm_max;
    return lim > (int32_t)XRF_ICO_WORD_MAG_MASK ? (int32_t)XRF_ICO_WORD_MAG_MASK : lim;
}

static inline uint16_t xrf_ico_out_word(int16_t pwm, uint8_t dout, int32_t lim)
{
    /* int32 so that |-32768| does not overflow. */
    int32_t mag = pwm < 0 ? -(int32_t)pwm : pwm;
    if (mag > lim)
        mag = lim;
    return (uint16_t)((uint32_t)mag | (pwm >= 0 ? XRF_ICO_WORD_DIR_BIT : 0u) |
                      (dout ? XRF_ICO_WORD_DOUT_BIT : 0u));
}

/* The ALL frame for out (lim from xrf_ico_mag_limit); sent_pwm gets the signed duty each word
 * carries, the limit applied. Every byte of the frame is written once, no memset. */
static inline void xrf_ico_encode_all_inline(const struct xrf_ico_out *out, int32_t lim,
                                             uint8_t frame[XRF_ICO_FRAME], int16_t sent_pwm[4])
{
    frame[0] = XRF_ICO_ALL;
    frame[1] = 0;
#pragma GCC unroll 4
    for (int ch = 0; ch < 4; ch++) {
        const uint16_t w = xrf_ico_out_word(out->pwm[ch], out->dout[ch], lim);
        frame[2 + 2 * ch] = (uint8_t)(w & 0xFF);
        frame[3 + 2 * ch] = (uint8_t)(w >> 8);
        const int16_t mag = (int16_t)(w & XRF_ICO_WORD_MAG_MASK);
        sent_pwm[ch] = (w & XRF_ICO_WORD_DIR_BIT) ? mag : (int16_t)-mag;
    }
    frame[10] = 0;
    frame[11] = 0;
}

static inline void xrf_ico_decode_all_inline(const uint8_t reply[XRF_ICO_FRAME],
                                             struct xrf_ico_in *in)
{
#pragma GCC unroll 4
    for (int ch = 0; ch < 4; ch++) {
        const uint32_t w = (uint32_t)reply[1 + 2 * ch] | ((uint32_t)reply[2 + 2 * ch] << 8);
        in->enc[ch] = (int32_t)(w & XRF_ICO_WORD_MAG_MASK);
        in->din[2 * ch] = (uint8_t)((w >> 14) & 1u);
        in->din[2 * ch + 1] = (uint8_t)((w >> 15) & 1u);
    }
}

/* A way to exchange one frame with a board. xfer is called from the real-time thread: it must
 * not allocate or block beyond the transfer itself. Returns 0 or -errno. */
struct xrf_ico_transport {
    const char *name;
    int (*xfer)(struct xrf_ico_transport *t, const uint8_t tx[XRF_ICO_FRAME],
                uint8_t rx[XRF_ICO_FRAME]);
    void (*close)(struct xrf_ico_transport *t); /* also frees t */
    /* A bench of several boards (channels.h: board b carries channels 4b+1 .. 4b+4): `boards`
     * of them, 1 .. XRF_MAX_BOARDS (0 reads as 1), and xfer_board exchanges the same 12-byte
     * frame with board b (0 .. boards - 1; -EINVAL beyond). xfer is board 0's exchange, which is
     * all XRF2's IcoIo uses. NULL xfer_board: one board. Same rules as xfer (real-time thread). */
    int boards;
    int (*xfer_board)(struct xrf_ico_transport *t, int board, const uint8_t tx[XRF_ICO_FRAME],
                      uint8_t rx[XRF_ICO_FRAME]);
};

/* Linux spidev: mode 0, 8 bits, speed_hz (XRF2: 31 MHz); bytes bit-reversed on the wire.
 * `devices` is one device per ico board, comma-separated, board 1 first ("/dev/spidev0.0" or
 * "/dev/spidev0.0,/dev/spidev0.1,/dev/spidev1.0"): the transport's `boards` is their count and
 * xfer_board(b) goes to the b-th. Each must be a character device (-ENOTTY otherwise, -EISDIR a
 * folder, -ENOENT missing); -E2BIG more than XRF_MAX_BOARDS, -EINVAL an empty or too long
 * (XRF_SPI_PATH_MAX) name. _bench also says which device failed (*failed: its 0-based index, -1
 * when none did). */
#define XRF_SPI_PATH_MAX 128
int xrf_spidev_open(const char *devices, uint32_t speed_hz, struct xrf_ico_transport **out);
int xrf_spidev_open_bench(const char *devices, uint32_t speed_hz, struct xrf_ico_transport **out,
                          int *failed);
/* EVL out-of-band spidev (only in builds with XRF_HAVE_EVL; elsewhere returns -ENOSYS). */
int xrf_evl_spidev_open(const char *device, uint32_t speed_hz, struct xrf_ico_transport **out);

#ifdef __cplusplus
}
#endif

#endif /* XRF_ICO_H */
