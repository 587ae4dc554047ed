/* Golden frames for the ico protocol, hand-computed from XRF2_API.md ("IcoIo"). */
#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "xrf/ico.h"

#define CHECK_NAME "test_ico_frames"
#include "check.h"

static int same(const uint8_t *a, const uint8_t *b)
{
    return memcmp(a, b, XRF_ICO_FRAME) == 0;
}

static void test_pwm_max(void)
{
    CHECK(xrf_ico_pwm_max(0.2) == 409);
    CHECK(xrf_ico_pwm_max(XRF_ICO_DEFAULT_PWM_LIMIT) == 409);
    CHECK(xrf_ico_pwm_max(1.0) == 2047);
    CHECK(xrf_ico_pwm_max(1.5) == 2047);
    CHECK(xrf_ico_pwm_max(0.0) == 0);
    CHECK(xrf_ico_pwm_max(-0.3) == 0);
    CHECK(xrf_ico_pwm_max(0.5) == 1023);
}

static void test_encode_all(void)
{
    struct xrf_ico_out out = {.pwm = {100, -100, 2047, -3000}, .dout = {1, 0, 0, 1}};
    uint8_t f[XRF_ICO_FRAME];
    memset(f, 0xEE, sizeof f);
    xrf_ico_encode_all(&out, 409, f);
    /* ch1 100|dir|dout = 0xC064; ch2 100 = 0x0064; ch3 409|dir = 0x4199; ch4 409|dout = 0x8199 */
    static const uint8_t golden[XRF_ICO_FRAME] = {0x03, 0x00, 0x64, 0xC0, 0x64, 0x00,
                                                  0x99, 0x41, 0x99, 0x81, 0x00, 0x00};
    CHECK(same(f, golden));

    /* Zero counts as positive (direction bit set); -32768 must not overflow the magnitude. */
    struct xrf_ico_out o2 = {.pwm = {0, -32768, 32767, 1}, .dout = {0, 0, 1, 0}};
    xrf_ico_encode_all(&o2, 2047, f);
    static const uint8_t golden2[XRF_ICO_FRAME] = {0x03, 0x00, 0x00, 0x40, 0xFF, 0x07,
                                                   0xFF, 0xC7, 0x01, 0x40, 0x00, 0x00};
    CHECK(same(f, golden2));

    /* A limit of 0 leaves only the direction and output bits. */
    xrf_ico_encode_all(&out, 0, f);
    static const uint8_t golden3[XRF_ICO_FRAME] = {0x03, 0x00, 0x00, 0xC0, 0x00, 0x00,
                                                   0x00, 0x40, 0x00, 0x80, 0x00, 0x00};
    CHECK(same(f, golden3));
}

static void test_decode_all(void)
{
    /* ch1 0x1234 (enc 4660), ch2 0xFFFF (enc 16383, both pins), ch3 0x4000 (enc 0, pin 1),
     * ch4 0x8001 (enc 1, pin 2). Byte 0 and bytes 9..11 are noise the parser must ignore. */
    static const uint8_t reply[XRF_ICO_FRAME] = {0xAB, 0x34, 0x12, 0xFF, 0xFF, 0x00,
                                                 0x40, 0x01, 0x80, 0x5A, 0x5A, 0x5A};
    struct xrf_ico_in in;
    memset(&in, 0x77, sizeof in);
    xrf_ico_decode_all(reply, &in);
    CHECK(in.enc[0] == 4660);
    CHECK(in.enc[1] == 16383);
    CHECK(in.enc[2] == 0);
    CHECK(in.enc[3] == 1);
    static const uint8_t din[8] = {0, 0, 1, 1, 1, 0, 0, 1};
    CHECK(memcmp(in.din, din, 8) == 0);
}

static void test_pwm_enc_ops(void)
{
    uint8_t f[XRF_ICO_FRAME];
    xrf_ico_encode_pwm(1, 300, 409, f);
    static const uint8_t g1[XRF_ICO_FRAME] = {0x04, 0, 0x2C, 0x41, 0, 0, 0, 0, 0, 0, 0, 0};
    CHECK(same(f, g1));
    xrf_ico_encode_pwm(4, -1000, 409, f);
    static const uint8_t g4[XRF_ICO_FRAME] = {0x07, 0, 0x99, 0x01, 0, 0, 0, 0, 0, 0, 0, 0};
    CHECK(same(f, g4));
    xrf_ico_encode_pwm(5, 100, 409, f);
    static const uint8_t noop[XRF_ICO_FRAME] = {0};
    CHECK(same(f, noop));
    xrf_ico_encode_pwm(0, 100, 409, f);
    CHECK(same(f, noop));

    static const uint8_t r[XRF_ICO_FRAME] = {0x99, 0x39, 0x30, 0, 0, 0, 0, 0, 0, 0, 0, 0};
    CHECK(xrf_ico_decode_enc(r) == 12345);
    static const uint8_t r2[XRF_ICO_FRAME] = {0, 0xFF, 0xFF, 0, 0, 0, 0, 0, 0, 0, 0, 0};
    CHECK(xrf_ico_decode_enc(r2) == 16383);

    xrf_ico_frame_op(XRF_ICO_INIT, f);
    static const uint8_t init[XRF_ICO_FRAME] = {1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0};
    CHECK(same(f, init));
}

static void test_test_pattern(void)
{
    uint8_t f[XRF_ICO_FRAME];
    xrf_ico_test_pattern(f);
    static const uint8_t g[XRF_ICO_FRAME] = {0x0C, 0x01, 0x02, 0x04, 0x08, 0x10,
                                             0x20, 0x40, 0x80, 0x35, 0xCA, 0x0F};
    CHECK(same(f, g));
    /* The expected echo is the payload; byte 0 is not compared. */
    uint8_t r[XRF_ICO_FRAME];
    memcpy(r, g, sizeof r);
    r[0] = 0x00;
    CHECK(xrf_ico_test_bit_errors(r) == 0);
    r[0] = 0xFF;
    CHECK(xrf_ico_test_bit_errors(r) == 0);
    r[3] ^= 0x81;
    r[11] ^= 0x01;
    CHECK(xrf_ico_test_bit_errors(r) == 3);
    static const uint8_t zeros[XRF_ICO_FRAME] = {0};
    CHECK(xrf_ico_test_bit_errors(zeros) == 8 + 4 + 4 + 4); /* popcount of the payload */
    /* A transport that forgot the bit reversal must fail. */
    uint8_t rev[XRF_ICO_FRAME];
    for (int i = 0; i < XRF_ICO_FRAME; i++)
        rev[i] = xrf_ico_bitrev8(g[i]);
    CHECK(xrf_ico_test_bit_errors(rev) > 0);
}

static void test_bitrev(void)
{
    CHECK(xrf_ico_bitrev8(0x01) == 0x80);
    CHECK(xrf_ico_bitrev8(0x80) == 0x01);
    CHECK(xrf_ico_bitrev8(0x03) == 0xC0);
    CHECK(xrf_ico_bitrev8(0x12) == 0x48);
    CHECK(xrf_ico_bitrev8(0xF0) == 0x0F);
    CHECK(xrf_ico_bitrev8(0xA5) == 0xA5);
    CHECK(xrf_ico_bitrev8(0x35) == 0xAC);
    int involution = 1;
    for (int b = 0; b < 256; b++) {
        uint8_t r = xrf_ico_bitrev8((uint8_t)b);
        if (xrf_ico_bitrev8(r) != b || __builtin_popcount(r) != __builtin_popcount(b))
            involution = 0;
    }
    CHECK(involution);
}

static void test_transport_open_errors(void)
{
    /* Start from a non-NULL pointer to see that a failed open clears it. */
    static struct xrf_ico_transport dummy;
    struct xrf_ico_transport *t = &dummy;
    CHECK(xrf_spidev_open("/nonexistent/spidev9.9", 31000000, &t) == -ENOENT && t == NULL);
    CHECK(xrf_spidev_open(NULL, 31000000, &t) == -EINVAL);
#ifndef XRF_HAVE_EVL
    t = &dummy;
    CHECK(xrf_evl_spidev_open("/dev/spidev0.0", 31000000, &t) == -ENOSYS && t == NULL);
#endif
}

/* A bench of several boards: one device per board, each opened and checked; the failing one
 * is named (its index), whatever comes before it is closed again. */
static void test_bench_open_errors(void)
{
    char file[] = "/tmp/xrf-spidev-test-XXXXXX";
    int fd = mkstemp(file);
    CHECK(fd >= 0);
    close(fd);
    char dir[] = "/tmp/xrf-spidev-dir-XXXXXX";
    CHECK(mkdtemp(dir) != NULL);
    struct xrf_ico_transport *t = NULL;
    int failed = 99;
    char list[256];
    /* A regular file is no device: refused before any ioctl is tried on it. */
    CHECK(xrf_spidev_open_bench(file, 31000000, &t, &failed) == -ENOTTY && failed == 0 && !t);
    CHECK(xrf_spidev_open_bench(dir, 31000000, &t, &failed) == -EISDIR && failed == 0);
    /* A character device that is not an SPI device: its ioctl says so. */
    CHECK(xrf_spidev_open_bench("/dev/null", 31000000, &t, &failed) == -ENOTTY && failed == 0);
    /* The second board's device missing: the first is not the one named. */
    snprintf(list, sizeof list, "%s,/nonexistent/spidev0.1", "/dev/null");
    CHECK(xrf_spidev_open_bench(list, 31000000, &t, &failed) == -ENOTTY && failed == 0);
    CHECK(xrf_spidev_open_bench("/nonexistent/spidev0.0", 31000000, &t, &failed) == -ENOENT &&
          failed == 0);
    /* The list itself: an empty name. */
    CHECK(xrf_spidev_open_bench("", 31000000, &t, &failed) == -EINVAL && failed == 0);
    CHECK(xrf_spidev_open_bench("/dev/null,,/dev/null", 31000000, &t, &failed) == -ENOTTY);
    CHECK(xrf_spidev_open_bench("/dev/null", 0, &t, &failed) == -EINVAL && failed == -1);
    unlink(file);
    rmdir(dir);
}

int main(void)
{
    test_pwm_max();
    test_encode_all();
    test_decode_all();
    test_pwm_enc_ops();
    test_test_pattern();
    test_bitrev();
    test_transport_open_errors();
    test_bench_open_errors();
    return check_summary();
}
