/* The simulated ico board: protocol answers, each injected fault, and plant sanity. Runs with a
 * fixed 1 ms step per transfer so every number is deterministic. */
#define _POSIX_C_SOURCE 200809L

#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "xrf/channels.h"
#include "xrf/plants.h"
#include "xrf/sim.h"

#define CHECK_NAME "test_sim_board"
#include "check.h"

#ifndef M_PI
#define M_PI 3.14159265358979323846
#endif

#define DT 0.001
#define LIMIT 409

static struct xrf_ico_transport *open_sim(int robot, const char *faults,
                                          struct xrf_sim_outputs *outputs)
{
    struct xrf_sim_faults f;
    MUST(xrf_sim_parse_faults(faults, &f) == 0);
    struct xrf_ico_transport *t = NULL;
    MUST(xrf_sim_open(robot, &f, DT, outputs, &t) == 0);
    MUST(t != NULL && strcmp(t->name, "sim") == 0);
    return t;
}

static void op(struct xrf_ico_transport *t, uint8_t code, uint8_t rx[XRF_ICO_FRAME])
{
    uint8_t tx[XRF_ICO_FRAME];
    xrf_ico_frame_op(code, tx);
    MUST(t->xfer(t, tx, rx) == 0);
}

static void all(struct xrf_ico_transport *t, int16_t p1, int16_t p2, const uint8_t dout[4],
                struct xrf_ico_in *in)
{
    struct xrf_ico_out out = {.pwm = {p1, p2, 0, 0}};
    if (dout)
        memcpy(out.dout, dout, 4);
    uint8_t tx[XRF_ICO_FRAME], rx[XRF_ICO_FRAME];
    xrf_ico_encode_all(&out, LIMIT, tx);
    MUST(t->xfer(t, tx, rx) == 0);
    xrf_ico_decode_all(rx, in);
}

/* Runs `ms` transfers of ALL with constant outputs; returns the last reply. */
static struct xrf_ico_in run(struct xrf_ico_transport *t, int16_t p1, int16_t p2, int ms)
{
    struct xrf_ico_in in;
    memset(&in, 0, sizeof in);
    for (int i = 0; i < ms; i++)
        all(t, p1, p2, NULL, &in);
    return in;
}

static double st(struct xrf_ico_transport *t, int i)
{
    double s[5];
    int n = xrf_sim_plant_state(t, s, 5);
    MUST(n > i);
    return s[i];
}

static void test_protocol(void)
{
    struct xrf_ico_transport *t = open_sim(XRF_SIM_JIWY, NULL, NULL);
    uint8_t rx[XRF_ICO_FRAME];
    op(t, XRF_ICO_INIT, rx);
    CHECK(rx[XRF_ICO_INIT_REPLY_BYTE] == XRF_ICO_INIT_REPLY);

    uint8_t tx[XRF_ICO_FRAME];
    xrf_ico_test_pattern(tx);
    CHECK(t->xfer(t, tx, rx) == 0);
    CHECK(xrf_ico_test_bit_errors(rx) == 0);
    CHECK(memcmp(&rx[1], &tx[1], XRF_ICO_FRAME - 1) == 0);

    /* tx and rx may alias. */
    xrf_ico_test_pattern(tx);
    CHECK(t->xfer(t, tx, tx) == 0);
    CHECK(xrf_ico_test_bit_errors(tx) == 0);

    op(t, XRF_ICO_NOOP, rx);
    static const uint8_t zeros[XRF_ICO_FRAME] = {0};
    CHECK(memcmp(rx, zeros, sizeof rx) == 0);

    /* Drive pan with PWM_1, read it back with ENC_1 and ALL: both agree. */
    xrf_ico_encode_pwm(1, 200, LIMIT, tx);
    CHECK(t->xfer(t, tx, rx) == 0);
    for (int i = 0; i < 50; i++)
        op(t, XRF_ICO_NOOP, rx);
    CHECK(st(t, 0) > 0.01);
    xrf_ico_encode_pwm(1, 0, LIMIT, tx);
    CHECK(t->xfer(t, tx, rx) == 0);
    for (int i = 0; i < 1000; i++)
        op(t, XRF_ICO_NOOP, rx);
    CHECK(st(t, 2) == 0.0); /* friction has stopped it */
    op(t, XRF_ICO_ENC_1, rx);
    int32_t e1 = xrf_ico_decode_enc(rx);
    CHECK(e1 > 0);
    struct xrf_ico_in in;
    all(t, 0, 0, NULL, &in);
    CHECK(in.enc[0] == e1);
    CHECK(in.enc[2] == 0 && in.enc[3] == 0);

    /* RESET zeroes the counters (the axis is at rest here)... */
    op(t, XRF_ICO_RESET, rx);
    CHECK(memcmp(rx, zeros, sizeof rx) == 0);
    op(t, XRF_ICO_ENC_1, rx);
    CHECK(xrf_ico_decode_enc(rx) == 0);
    /* ...and switches the outputs off: the drive set just before acts for one step only. */
    xrf_ico_encode_pwm(1, 300, LIMIT, tx);
    CHECK(t->xfer(t, tx, rx) == 0);
    op(t, XRF_ICO_RESET, rx);
    for (int i = 0; i < 500; i++)
        op(t, XRF_ICO_NOOP, rx);
    double pan = st(t, 0);
    CHECK(st(t, 2) == 0.0);
    for (int i = 0; i < 500; i++)
        op(t, XRF_ICO_NOOP, rx);
    CHECK(st(t, 0) == pan);
    op(t, XRF_ICO_RESET, rx);
    all(t, 0, 0, NULL, &in);
    CHECK(in.enc[0] == 0 && in.enc[1] == 0);
    static const uint8_t no_inputs[8] = {0};
    CHECK(memcmp(in.din, no_inputs, 8) == 0); /* nothing is wired to the pins */

    double s[8];
    CHECK(xrf_sim_plant_state(t, s, 8) == 4);
    CHECK(xrf_sim_plant_state(t, s, 2) == 2);
    t->close(t);
}

static void test_faults(void)
{
    uint8_t tx[XRF_ICO_FRAME], rx[XRF_ICO_FRAME];
    struct xrf_ico_in in;

    struct xrf_ico_transport *t = open_sim(XRF_SIM_RELBOT, "no_init", NULL);
    op(t, XRF_ICO_INIT, rx);
    CHECK(rx[XRF_ICO_INIT_REPLY_BYTE] != XRF_ICO_INIT_REPLY);
    t->close(t);

    t = open_sim(XRF_SIM_RELBOT, "corrupt_echo", NULL);
    xrf_ico_test_pattern(tx);
    CHECK(t->xfer(t, tx, rx) == 0);
    CHECK(xrf_ico_test_bit_errors(rx) > 0);
    op(t, XRF_ICO_INIT, rx);
    CHECK(rx[XRF_ICO_INIT_REPLY_BYTE] == XRF_ICO_INIT_REPLY);
    t->close(t);

    t = open_sim(XRF_SIM_RELBOT, "dead_encoder=1", NULL);
    in = run(t, 300, -300, 500);
    CHECK(in.enc[0] == 0);
    CHECK(in.enc[1] != 0);
    CHECK(st(t, 0) > 0.05); /* the wheel turns, only its encoder is dead */
    t->close(t);

    t = open_sim(XRF_SIM_RELBOT, "stuck_input=3:1,stuck_input=8:0", NULL);
    in = run(t, 0, 0, 3);
    static const uint8_t only_pin3[8] = {0, 0, 1, 0, 0, 0, 0, 0};
    CHECK(memcmp(in.din, only_pin3, 8) == 0);
    t->close(t);

    /* PWM_n sets the channel's digital output from bit 15 of its word, like ALL. */
    t = open_sim(XRF_SIM_RELBOT, "loopback=3", NULL);
    xrf_ico_encode_pwm(3, 0, LIMIT, tx);
    tx[3] |= 0x80;
    CHECK(t->xfer(t, tx, rx) == 0);
    op(t, XRF_ICO_NOOP, rx);
    struct xrf_ico_out keep = {.pwm = {0}, .dout = {0, 0, 1, 0}};
    xrf_ico_encode_all(&keep, LIMIT, tx);
    CHECK(t->xfer(t, tx, rx) == 0);
    xrf_ico_decode_all(rx, &in);
    CHECK(in.din[4] == 1);
    xrf_ico_encode_pwm(3, 0, LIMIT, tx);
    CHECK(t->xfer(t, tx, rx) == 0);
    all(t, 0, 0, NULL, &in);
    CHECK(in.din[4] == 0);
    t->close(t);

    /* Loopback: the reply is latched before the frame's outputs apply, so it shows the
     * previous frame's output. */
    t = open_sim(XRF_SIM_RELBOT, "loopback=2", NULL);
    static const uint8_t d2[4] = {0, 1, 0, 0}, d13[4] = {1, 0, 1, 0};
    all(t, 0, 0, d2, &in);
    CHECK(in.din[2] == 0);
    all(t, 0, 0, d2, &in);
    CHECK(in.din[2] == 1);
    CHECK(in.din[3] == 0 && in.din[0] == 0);
    all(t, 0, 0, d13, &in);
    all(t, 0, 0, d13, &in);
    CHECK(in.din[2] == 0 && in.din[0] == 0 && in.din[4] == 0); /* only channel 2 is wired */
    t->close(t);

    t = open_sim(XRF_SIM_JIWY, "slow_link_us=3000", NULL);
    struct timespec a, b;
    clock_gettime(CLOCK_MONOTONIC, &a);
    for (int i = 0; i < 5; i++)
        op(t, XRF_ICO_NOOP, rx);
    clock_gettime(CLOCK_MONOTONIC, &b);
    double us = (double)(b.tv_sec - a.tv_sec) * 1e6 + (double)(b.tv_nsec - a.tv_nsec) / 1e3;
    CHECK(us >= 5 * 3000.0);
    t->close(t);

    /* Reversed motor: the same drive turns pan the other way. */
    t = open_sim(XRF_SIM_JIWY, "reversed_motor=1", NULL);
    run(t, 150, 150, 100);
    CHECK(st(t, 0) < -0.01);
    CHECK(st(t, 1) > 0.01);
    t->close(t);

    /* Reversed right motor on the RELbot: "straight" drive spins it on the spot. */
    t = open_sim(XRF_SIM_RELBOT, "reversed_motor=2", NULL);
    run(t, 300, -300, 1000);
    CHECK(fabs(st(t, 2)) > 1.0);
    CHECK(st(t, 3) > 0 && st(t, 4) < 0);
    t->close(t);
}

static void test_parse(void)
{
    struct xrf_sim_faults f;
    CHECK(xrf_sim_parse_faults("dead_encoder=2,reversed_motor=1,no_init,corrupt_echo,"
                               "stuck_input=3:1,slow_link_us=200,loopback=1",
                               &f) == 0);
    CHECK(f.dead_encoder == 2 && f.reversed_motor == 1 && f.no_init_reply == 1);
    CHECK(f.corrupt_echo == 1 && f.stuck_input == 4 && f.stuck_value == 4);
    CHECK(f.slow_link_us == 200 && f.loopback == 1);
    CHECK(xrf_sim_parse_faults(" dead_encoder=1 , dead_encoder=4 ,", &f) == 0);
    CHECK(f.dead_encoder == 9);
    CHECK(xrf_sim_parse_faults("start=4294967295", &f) == 0 && f.start_seed == 4294967295u);
    CHECK(xrf_sim_parse_faults("start=0", &f) == -EINVAL && f.start_seed == 0);
    CHECK(xrf_sim_parse_faults("", &f) == 0 && f.dead_encoder == 0);
    CHECK(xrf_sim_parse_faults(NULL, &f) == 0);
    CHECK(xrf_sim_parse_faults("dead_encoder=5", &f) == -EINVAL);
    CHECK(xrf_sim_parse_faults("dead_encoder=0", &f) == -EINVAL);
    CHECK(xrf_sim_parse_faults("stuck_input=9:1", &f) == -EINVAL);
    CHECK(xrf_sim_parse_faults("stuck_input=3", &f) == -EINVAL);
    CHECK(xrf_sim_parse_faults("stuck_input=3:2", &f) == -EINVAL);
    CHECK(xrf_sim_parse_faults("slow_link_us=abc", &f) == -EINVAL);
    CHECK(xrf_sim_parse_faults("warp_drive", &f) == -EINVAL);
    CHECK(xrf_sim_robot_from_name("relbot") == XRF_SIM_RELBOT);
    CHECK(xrf_sim_robot_from_name("jiwy") == XRF_SIM_JIWY);
    CHECK(xrf_sim_robot_from_name("warthog") == -EINVAL);
    struct xrf_ico_transport *t = NULL;
    CHECK(xrf_sim_open(7, NULL, DT, NULL, &t) == -EINVAL && t == NULL);
}

static void test_relbot_physics(void)
{
    struct xrf_ico_transport *t = open_sim(XRF_SIM_RELBOT, NULL, NULL);
    run(t, 300, -300, 20);
    double w_early = st(t, 3);
    run(t, 300, -300, 980);
    double w_1s = st(t, 3);
    struct xrf_ico_in in = run(t, 300, -300, 1000);
    double w_2s = st(t, 3);
    CHECK(w_early > 0 && w_early < w_1s);                  /* accelerating */
    CHECK(fabs(w_2s - w_1s) < 0.01 * w_2s);                /* settled */
    CHECK(w_2s > 1.0 && w_2s < 20.0);                      /* a plausible wheel speed, rad/s */
    CHECK(fabs(st(t, 4) - w_2s) < 1e-9);                   /* mirrored motor, same speed forward */
    CHECK(st(t, 0) > 0.2);                                 /* x grows */
    CHECK(fabs(st(t, 1)) < 1e-9 && fabs(st(t, 2)) < 1e-9); /* straight */
    /* Left encoder counts up, right one down (it wrapped below zero). */
    CHECK(in.enc[0] > 0 && in.enc[0] < 16384);
    struct xrf_ico_in in2 = run(t, 300, -300, 1);
    int d1 = (in2.enc[0] - in.enc[0] + 16384) % 16384;
    int d2 = (in.enc[1] - in2.enc[1] + 16384) % 16384;
    CHECK(d1 > 0 && d1 < 8192 && d2 > 0 && d2 < 8192 && abs(d1 - d2) <= 1);

    /* Outputs off: friction and the shorted armature stop it, and it stays put. */
    run(t, 0, 0, 2000);
    CHECK(st(t, 3) == 0.0 && st(t, 4) == 0.0);
    double x = st(t, 0);
    run(t, 0, 0, 100);
    CHECK(st(t, 0) == x);

    /* Only the left wheel driving: the robot turns clockwise (theta decreases). */
    run(t, 300, 0, 500);
    CHECK(st(t, 2) < -0.1);
    t->close(t);
}

static void test_jiwy_physics(void)
{
    struct xrf_ico_transport *t = open_sim(XRF_SIM_JIWY, NULL, NULL);
    const double pan_stop = M_PI / 2, tilt_stop = M_PI / 4;
    /* Drive into the positive stops, watching the pan encoder wrap on the way. */
    struct xrf_ico_in in, prev;
    memset(&prev, 0, sizeof prev);
    int wraps = 0, in_range = 1;
    for (int i = 0; i < 3000; i++) {
        all(t, LIMIT, LIMIT, NULL, &in);
        if (prev.enc[0] - in.enc[0] > 8192)
            wraps++;
        if (in.enc[0] < 0 || in.enc[0] >= 16384)
            in_range = 0;
        prev = in;
        if (i == 30) {
            CHECK(st(t, 2) > 0.1); /* moving at the camera */
        }
    }
    CHECK(wraps == 1 && in_range);
    CHECK(fabs(st(t, 0) - pan_stop) < 1e-12);
    CHECK(fabs(st(t, 1) - tilt_stop) < 1e-12);
    CHECK(st(t, 2) == 0.0 && st(t, 3) == 0.0);
    /* 90 degrees of pan is 19/4 motor turns = 19456 counts -> 3072 after the wrap. */
    CHECK(abs(in.enc[0] - 3072) <= 1);
    /* 45 degrees of tilt is 76/8 motor turns = 38912 counts -> 6144 after two wraps. */
    CHECK(abs(in.enc[1] - 6144) <= 1);

    /* And the other way. */
    run(t, -LIMIT, -LIMIT, 3000);
    CHECK(fabs(st(t, 0) + pan_stop) < 1e-12);
    CHECK(fabs(st(t, 1) + tilt_stop) < 1e-12);
    CHECK(st(t, 2) == 0.0 && st(t, 3) == 0.0);

    /* A small drive settles at a steady camera rate before reaching a stop. */
    run(t, 0, 0, 500);
    run(t, 60, 0, 150);
    double r1 = st(t, 2);
    run(t, 60, 0, 50);
    double r2 = st(t, 2);
    CHECK(r1 > 0.1 && fabs(r2 - r1) < 0.02 * r2);
    CHECK(st(t, 0) < pan_stop);
    t->close(t);
}

static void test_outputs(void)
{
    struct xrf_sim_outputs o;
    memset(&o, 0, sizeof o);
    struct xrf_ico_transport *t = open_sim(XRF_SIM_RELBOT, NULL, &o);
    CHECK(o.active == 1);
    static const uint8_t d[4] = {1, 0, 0, 1};
    struct xrf_ico_in in;
    for (int i = 0; i < 500; i++)
        all(t, 300, -300, d, &in);
    CHECK(o.pwm[0] == 300 && o.pwm[1] == -300 && o.pwm[2] == 0);
    CHECK(o.dout[0] == 1 && o.dout[3] == 1 && o.dout[1] == 0);
    CHECK(o.plant[0] == st(t, 0) && o.plant[0] > 0.0 && o.plant[2] == st(t, 2));

    o.forced_off = 1;
    for (int i = 0; i < 2000; i++)
        all(t, 300, -300, d, &in);
    CHECK(o.pwm[0] == 0 && o.pwm[1] == 0 && o.dout[0] == 0);
    CHECK(st(t, 3) == 0.0 && st(t, 4) == 0.0);
    double x = st(t, 0);
    run(t, 300, -300, 200);
    CHECK(st(t, 0) == x);
    /* The safe reaction `brake` leaves the brake's output on while forced: the pins show
     * forced_dout, whatever the frames ask. */
    o.forced_dout[2] = 1;
    all(t, 300, -300, d, &in);
    CHECK(o.dout[2] == 1 && o.dout[0] == 0 && o.dout[3] == 0 && o.pwm[0] == 0);
    t->close(t);
    CHECK(o.active == 0);

    memset(&o, 0, sizeof o);
    t = open_sim(XRF_SIM_JIWY, NULL, &o);
    run(t, 100, -100, 100);
    CHECK(o.plant[0] == st(t, 0) && o.plant[1] == st(t, 1));
    CHECK(o.plant[0] > 0 && o.plant[1] < 0);
    t->close(t);
}

/* A bench wider than one board (issue 29 item 2): board b answers for channels 4b+1 .. 4b+4, only
 * board 0's transfer moves the plant, channels beyond the bench read 0 and drive nothing. */
static void board_all(struct xrf_ico_transport *t, int board, int16_t p1, struct xrf_ico_in *in)
{
    struct xrf_ico_out out = {.pwm = {p1, 0, 0, 0}, .dout = {1, 0, 0, 0}};
    uint8_t tx[XRF_ICO_FRAME], rx[XRF_ICO_FRAME];
    xrf_ico_encode_all(&out, LIMIT, tx);
    MUST(t->xfer_board(t, board, tx, rx) == 0);
    xrf_ico_decode_all(rx, in);
}

static void test_bench_channels(void)
{
    struct xrf_ico_transport *t = NULL;
    CHECK(xrf_sim_open_bench(XRF_SIM_RELBOT, XRF_MAX_CHANNELS + 1, NULL, DT, NULL, &t) == -EINVAL);
    CHECK(xrf_sim_open_bench(XRF_SIM_RELBOT, 3, NULL, DT, NULL, &t) == -EINVAL && t == NULL);
    CHECK(xrf_sim_open_bench(XRF_SIM_RELBOT, -1, NULL, DT, NULL, &t) == -EINVAL);
    /* One board for a 4-channel row; a frame to a board that is not there is refused. */
    t = open_sim(XRF_SIM_RELBOT, NULL, NULL);
    CHECK(t->boards == 1);
    uint8_t tx[XRF_ICO_FRAME], rx[XRF_ICO_FRAME];
    xrf_ico_frame_op(XRF_ICO_NOOP, tx);
    CHECK(t->xfer_board(t, 1, tx, rx) == -EINVAL && t->xfer_board(t, -1, tx, rx) == -EINVAL);
    t->close(t);

    struct xrf_sim_outputs o;
    memset(&o, 0, sizeof o);
    MUST(xrf_sim_open_bench(XRF_SIM_RELBOT, XRF_MAX_CHANNELS, NULL, DT, &o, &t) == 0);
    CHECK(t->boards == XRF_MAX_BOARDS);
    CHECK(t->xfer_board(t, XRF_MAX_BOARDS, tx, rx) == -EINVAL);
    struct xrf_ico_in in;
    run(t, 300, -300, 200); /* RELbot's wheels face each other: this is forward */
    const double x = st(t, 0);
    CHECK(x > 0.0);
    /* Board 2's frames: its channel 1 is the bench's channel 9, mirrored there; the plant waits
     * for board 0's next transfer. */
    for (int i = 0; i < 200; i++)
        board_all(t, 2, -250, &in);
    CHECK(st(t, 0) == x);
    CHECK(o.pwm[8] == -250 && o.dout[8] == 1 && o.pwm[0] == 300 && o.pwm[4] == 0);
    CHECK(in.enc[0] == 0 && in.enc[3] == 0); /* nothing wired on channels 9..12 */
    all(t, 300, -300, NULL, &in);
    CHECK(st(t, 0) > x);
    /* The safety watcher forces every channel of the bench off. */
    o.forced_off = 1;
    board_all(t, 2, -250, &in);
    CHECK(o.pwm[8] == 0 && o.dout[8] == 0);
    t->close(t);

    /* A 9-channel bench: board 2 carries channel 9 only; 10..12 are not the bench's. */
    memset(&o, 0, sizeof o);
    MUST(xrf_sim_open_bench(XRF_SIM_RELBOT, 9, NULL, DT, &o, &t) == 0);
    CHECK(t->boards == 3);
    struct xrf_ico_out out = {.pwm = {100, 200, 300, 400}, .dout = {1, 1, 1, 1}};
    xrf_ico_encode_all(&out, LIMIT, tx);
    MUST(t->xfer_board(t, 2, tx, rx) == 0);
    CHECK(o.pwm[8] == 100 && o.pwm[9] == 0 && o.pwm[11] == 0 && o.dout[9] == 0);
    t->close(t);
}

/* The channel count in a segment is the loop's to rewrite: a reader takes it bounded. */
static void test_hostile_channel_count(void)
{
    struct xrf_shm *shm = calloc(1, sizeof *shm);
    MUST(shm != NULL);
    xrf_shm_init(shm);
    struct xrf_shm_geom g;
    CHECK(xrf_shm_check(shm, sizeof *shm, &g) == 0 && g.channels == XRF_ICO_CHANNELS);
    shm->channels = XRF_MAX_CHANNELS;
    CHECK(xrf_shm_check(shm, sizeof *shm, &g) == 0 && g.channels == XRF_MAX_CHANNELS);
    static const uint32_t hostile[] = {0, XRF_MAX_CHANNELS + 1, 1000, 0xFFFFFFFFu};
    for (size_t i = 0; i < sizeof hostile / sizeof hostile[0]; i++) {
        shm->channels = hostile[i];
        g.channels = 77;
        CHECK(xrf_shm_check(shm, sizeof *shm, &g) == -EPROTO && g.channels == 77);
        uint32_t n = xrf_shm_channels(shm);
        CHECK(n >= 1 && n <= XRF_MAX_CHANNELS);
    }
    shm->channels = 9;
    CHECK(xrf_shm_channels(shm) == 9);
    free(shm);
}

static void test_real_clock(void)
{
    /* Without fixed_dt the plant follows CLOCK_MONOTONIC. */
    struct xrf_sim_faults f = {0};
    struct xrf_ico_transport *t = NULL;
    CHECK(xrf_sim_open(XRF_SIM_JIWY, &f, 0.0, NULL, &t) == 0);
    struct xrf_ico_in in;
    all(t, LIMIT, 0, NULL, &in);
    struct timespec sl = {0, 20 * 1000 * 1000};
    nanosleep(&sl, NULL);
    all(t, LIMIT, 0, NULL, &in);
    CHECK(st(t, 0) > 0.0);
    t->close(t);
}

static double now_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

/* RELbot's x after two transfers `dt` apart from rest, the second with the first's outputs in force
 * for `dt`: the fixed-step board's answer for a gap of `dt`. */
static double relbot_x_after(double dt)
{
    struct xrf_sim_faults f = {0};
    struct xrf_ico_transport *t = NULL;
    MUST(xrf_sim_open(XRF_SIM_RELBOT, &f, dt, NULL, &t) == 0);
    struct xrf_ico_in in;
    all(t, 300, -300, NULL, &in);
    all(t, 300, -300, NULL, &in);
    double x = st(t, 0);
    t->close(t);
    return x;
}

/* A stall of the loop (an overrun: it skips to the next period boundary, the periods passed over
 * counted missed) is time the plant lives through: the board advances it over the whole gap, not
 * 50 ms of it, as a real one driven by the FPGA's last outputs. The gap the board measured lies
 * between the two clock readings around the sleep and the two around both transfers. */
static void test_a_stall_is_lived_through(void)
{
    struct xrf_sim_faults f = {0};
    struct xrf_ico_transport *t = NULL;
    CHECK(xrf_sim_open(XRF_SIM_RELBOT, &f, 0.0, NULL, &t) == 0);
    struct xrf_ico_in in;
    double m0 = now_s();
    all(t, 300, -300, NULL, &in); /* the first transfer: no time before it */
    double m1 = now_s();
    struct timespec big = {0, 300 * 1000 * 1000};
    nanosleep(&big, NULL);
    double m2 = now_s();
    all(t, 300, -300, NULL, &in);
    double m3 = now_s();
    double x = st(t, 0);
    t->close(t);
    double lo = relbot_x_after(m2 - m1), hi = relbot_x_after(m3 - m0 < 1.0 ? m3 - m0 : 1.0);
    CHECK(lo > 2.0 * relbot_x_after(0.050)); /* far more than 50 ms of it */
    CHECK(x >= lo * (1 - 1e-6) && x <= hi * (1 + 1e-6));
    if (!(x >= lo * (1 - 1e-6) && x <= hi * (1 + 1e-6)))
        fprintf(stderr, "x %.9g not in [%.9g, %.9g] (50 ms: %.9g)\n", x, lo, hi,
                relbot_x_after(0.05));
}

/* The plant table: ids from 1, names unique and found again by name, every row opens a board
 * whose state has the length its row says. */
static void test_plant_table(void)
{
    int n = xrf_plant_count();
    CHECK(n >= 2);
    struct xrf_plant_info info;
    CHECK(xrf_plant_describe(0, &info) == -EINVAL);
    CHECK(xrf_plant_describe(n + 1, &info) == -EINVAL);
    CHECK(xrf_plant_describe(1, NULL) == -EINVAL);
    CHECK(xrf_plant_describe(XRF_SIM_RELBOT, &info) == 0 && strcmp(info.name, "relbot") == 0);
    CHECK(xrf_plant_describe(XRF_SIM_JIWY, &info) == 0 && strcmp(info.name, "jiwy") == 0);
    for (int id = 1; id <= n; id++) {
        CHECK(xrf_plant_describe(id, &info) == 0 && info.id == id);
        CHECK(info.axes >= 1 && info.axes <= 12 && info.state_len >= 1 && info.state_len <= 8);
        CHECK(xrf_plant_id(info.name) == id && xrf_sim_robot_from_name(info.name) == id);
        struct xrf_ico_transport *t = open_sim(id, NULL, NULL);
        double s[8];
        CHECK(xrf_sim_plant_state(t, s, 8) == info.state_len);
        t->close(t);
    }
    CHECK(xrf_plant_id("RELBOT") == XRF_SIM_RELBOT);
    CHECK(xrf_plant_id(NULL) == -EINVAL);
    char names[256];
    int len = xrf_plant_names(names, sizeof names);
    CHECK(len == (int)strlen(names) && strncmp(names, "relbot, jiwy", 12) == 0);
    char tiny[4];
    CHECK(xrf_plant_names(tiny, sizeof tiny) == len && strcmp(tiny, "rel") == 0);
}

/* The production cell: `start=<seed>` draws poses over the whole travel; the home switch (pin 1
 * of each channel) reads closed exactly where the plant's position (from the switch edge) is
 * <= 0, the far-end switch near the high stop; driving every axis down closes every home switch,
 * and the switches stop a plant that starts on none of them. */
static void test_cell(void)
{
    int id = xrf_plant_id("cell");
    CHECK(id > 0);
    char spec[32];
    double lo[3] = {1e9, 1e9, 1e9}, hi[3] = {-1e9, -1e9, -1e9};
    int started_on_switch = 0;
    for (unsigned seed = 1; seed <= 200; seed++) {
        snprintf(spec, sizeof spec, "start=%u", seed);
        struct xrf_ico_transport *t = open_sim(id, spec, NULL);
        struct xrf_ico_in in;
        all(t, 0, 0, NULL, &in);
        double s[6];
        CHECK(xrf_sim_plant_state(t, s, 6) == 6);
        for (int a = 0; a < 3; a++) {
            lo[a] = s[a] < lo[a] ? s[a] : lo[a];
            hi[a] = s[a] > hi[a] ? s[a] : hi[a];
            CHECK(in.din[2 * a] == (s[a] <= 0.0));
            started_on_switch += in.din[2 * a];
        }
        t->close(t);
    }
    /* Table: switch edge 0.10 rad above the low stop, travel 4.71 rad; press/feeder 5 mm zones. */
    CHECK(lo[0] < -0.05 && hi[0] > 4.4 && lo[0] >= -0.1 - 1e-9 && hi[0] <= 1.5 * M_PI - 0.1);
    CHECK(lo[1] < 0.0 && hi[1] > 0.13 && hi[2] > 0.18);
    CHECK(started_on_switch > 0);
    /* The same seed, the same pose; another seed, another. */
    struct xrf_ico_transport *a = open_sim(id, "start=77", NULL);
    struct xrf_ico_transport *b = open_sim(id, "start=77", NULL);
    struct xrf_ico_transport *c = open_sim(id, "start=78", NULL);
    double sa[6], sb[6], sc[6];
    xrf_sim_plant_state(a, sa, 6);
    xrf_sim_plant_state(b, sb, 6);
    xrf_sim_plant_state(c, sc, 6);
    CHECK(memcmp(sa, sb, sizeof sa) == 0 && sa[0] != sc[0]);
    b->close(b);
    c->close(c);
    /* Drive all three axes down at 15 % for 8 s: every home switch closes, no far switch. */
    struct xrf_ico_in in;
    for (int i = 0; i < 8000; i++) {
        struct xrf_ico_out out = {.pwm = {-300, -300, -300, 0}};
        uint8_t tx[XRF_ICO_FRAME], rx[XRF_ICO_FRAME];
        xrf_ico_encode_all(&out, LIMIT, tx);
        MUST(a->xfer(a, tx, rx) == 0);
        xrf_ico_decode_all(rx, &in);
    }
    CHECK(in.din[0] && in.din[2] && in.din[4] && !in.din[1] && !in.din[3] && !in.din[5]);
    CHECK(!in.din[6] && !in.din[7]);
    a->close(a);
    /* Other plants wire nothing to the pins. */
    struct xrf_ico_transport *j = open_sim(XRF_SIM_JIWY, "start=5", NULL);
    all(j, 0, 0, NULL, &in);
    for (int k = 0; k < 8; k++)
        CHECK(in.din[k] == 0);
    j->close(j);
}

int main(void)
{
    test_plant_table();
    test_protocol();
    test_faults();
    test_parse();
    test_relbot_physics();
    test_jiwy_physics();
    test_outputs();
    test_real_clock();
    test_a_stall_is_lived_through();
    test_cell();
    test_bench_channels();
    test_hostile_channel_count();
    return check_summary();
}
