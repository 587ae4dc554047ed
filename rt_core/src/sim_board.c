/*
 * sim_board.c — a simulated ico board: answers the 12-byte protocol as the FPGA does and drives
 * a plant model advanced at each transfer. Faults are injected here, at the board's pins, so
 * the framework sees exactly what broken hardware would show it. The plant is whichever row of
 * the plant table (plants.c) was asked for: nothing here knows one plant from another.
 * See docs/rt_core/simulator.md.
 */
#define _POSIX_C_SOURCE 200809L

#include <errno.h>
#include <math.h>
#include <stddef.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "plant.h"
#include "xrf/plants.h"
#include "xrf/sim.h"

#ifndef M_PI
#define M_PI 3.14159265358979323846
#endif

#define SIM_COUNTS_PER_REV 4096.0 /* 1024-line encoder, quadrature */
#define SIM_MAX_SUBSTEP_S 100e-6
#define SIM_STALL_EVERY 100u /* faults.stall_ms: which transfers are held */
/* In real time the plant moves on over all the time since the previous transfer, as a real one
 * driven by the FPGA's last outputs does: after an overrun the loop skips to the next period
 * boundary and counts the periods passed over as missed (the grading clock is cycles + missed), so
 * a shorter clamp left the plant behind that clock (it used to be 50 ms). A gap longer than this
 * is a process stopped (a debugger, SIGSTOP; a hang ends at the watcher's 200 ms): the plant does
 * not run away for minutes, and one transfer's sub-steps stay bounded (10 000). */
#define SIM_MAX_GAP_S 1.0
/* On the loop's simulated clock (its thread's CPU time plus an offset) no period is skipped for
 * the host's sake: a gap is the loop's own computing, and the 50 ms clamp stays as it was. */
#define SIM_MAX_GAP_VIRTUAL_S 0.050

struct sim_board {
    struct xrf_ico_transport t;      /* first, so the transport pointer is the object pointer */
    const struct xrf_plant_ops *ops; /* the plant's row of the plant table (plants.c) */
    struct xrf_sim_faults faults;
    double fixed_dt;
    struct xrf_sim_outputs *outputs;
    struct xrf_sim_snapshot *snapshot; /* NULL, or where the plant's snapshot goes each transfer */
    int64_t (*clock)(void); /* simulated time: the loop's clock (xrf_sim_set_clock); NULL: real */

    int channels;       /* the bench's count, the plant row's (1..XRF_MAX_CHANNELS) */
    uint32_t transfers; /* counted for faults.stall_ms */

    /* The board's registers, channels 1..channels (the rest stay zero). */
    int16_t pwm[XRF_MAX_CHANNELS]; /* signed duty as decoded, magnitude up to 14 bits */
    uint8_t dout[XRF_MAX_CHANNELS];
    double enc_zero[XRF_MAX_CHANNELS]; /* motor angle at the last RESET (the counters' zero) */

    struct timespec last;
    int have_last;

    /* xrf_sim_follow: the loop's segment this board mirrors until the first output frame. */
    const struct xrf_shm *follow;
    uint32_t follow_seq;   /* the snapshot's seq last taken */
    uint32_t inject_reset; /* bit b: RESET board b first (xrf_sim_inject_reset, any thread) */

    max_align_t plant[]; /* the plant's own struct, ops->size bytes, allocated with the board */
};

static double ts_diff(const struct timespec *a, const struct timespec *b)
{
    return (double)(a->tv_sec - b->tv_sec) + 1e-9 * (double)(a->tv_nsec - b->tv_nsec);
}

static double motor_angle(const struct sim_board *s, int ch)
{
    return s->ops->motor_angle(s->plant, ch);
}

static int forced_off(const struct sim_board *s)
{
    return s->outputs && __atomic_load_n(&s->outputs->forced_off, __ATOMIC_RELAXED) != 0;
}

static void advance(struct sim_board *s, double dt)
{
    if (!(dt > 0.0))
        return;
    double duty[XRF_MAX_CHANNELS] = {0};
    if (!forced_off(s)) {
        for (int ch = 0; ch < s->channels; ch++) {
            double d = s->pwm[ch] / (double)XRF_ICO_PWM_FULL;
            /* The 14-bit field can hold more than full scale; the PWM saturates at 100 %. */
            if (d > 1.0)
                d = 1.0;
            else if (d < -1.0)
                d = -1.0;
            if (s->faults.reversed_motor & (1u << ch))
                d = -d;
            duty[ch] = d;
        }
    }
    int n = (int)ceil(dt / SIM_MAX_SUBSTEP_S);
    double h = dt / n;
    for (int i = 0; i < n; i++)
        s->ops->step(s->plant, duty, h);
}

static uint16_t encoder(const struct sim_board *s, int ch)
{
    if (ch >= s->channels)
        return 0;
    if (s->faults.dead_encoder & (1u << ch))
        return 0;
    double a = motor_angle(s, ch);
    if (isnan(a))
        return 0;
    double counts = floor((a - s->enc_zero[ch]) * (SIM_COUNTS_PER_REV / (2.0 * M_PI)));
    /* fmod keeps the sign of the dividend; shift negatives into 0..16383. */
    double w = fmod(counts, (double)XRF_ICO_ENC_MODULO);
    if (w < 0)
        w += XRF_ICO_ENC_MODULO;
    return (uint16_t)w;
}

/* Digital output ch as the pins see it: while forced off, what the watcher left there (the
 * brake's output for the safe reaction `brake`), else the last frame's. */
static int dout_now(const struct sim_board *s, int ch)
{
    if (forced_off(s))
        return __atomic_load_n(&s->outputs->forced_dout[ch], __ATOMIC_RELAXED) != 0;
    return s->dout[ch] != 0;
}

/* Input pin k (0..7 in xrf_ico_in.din order): a stuck fault, else the loopback plug, else the
 * plant's own switches (plants with an `inputs` op; nothing is wired on the others). */
static int input_pin(const struct sim_board *s, int k)
{
    if (s->faults.stuck_input & (1u << k))
        return (s->faults.stuck_value >> k) & 1u;
    int ch = k / 2;
    if ((k & 1) == 0 && (s->faults.loopback & (1u << ch)))
        return dout_now(s, ch);
    if (s->ops->inputs)
        return (s->ops->inputs(s->plant) >> k) & 1u;
    return 0;
}

static uint16_t in_word(const struct sim_board *s, int ch)
{
    if (ch >= s->channels) /* a channel the bench does not have: nothing is wired there */
        return 0;
    uint16_t w = encoder(s, ch);
    if (input_pin(s, 2 * ch))
        w |= 0x4000u;
    if (input_pin(s, 2 * ch + 1))
        w |= 0x8000u;
    return w;
}

static void put_le16(uint8_t *p, uint16_t w)
{
    p[0] = (uint8_t)(w & 0xFF);
    p[1] = (uint8_t)(w >> 8);
}

static int16_t word_pwm(uint16_t w)
{
    int16_t mag = (int16_t)(w & 0x3FFFu);
    return (w & 0x4000u) ? mag : (int16_t)-mag;
}

/* RESET of the board whose channels start at base. Its range is computed once and the registers
 * cleared with memset: the single loop of `ch = base; ch < base + 4 && ch < channels` that did
 * all three was compiled by GCC 12 -O2 so that, depending on the flags (with or without -fwrapv,
 * as the cffi build takes Python's CFLAGS), the board's registers or its counters' zero were left
 * as they were (found by the watcher's real-bench test, tests/rt_core/test_hold_board.py). */
static void reset_board(struct sim_board *s, int base)
{
    int end = base + XRF_ICO_CHANNELS;
    if (end > s->channels)
        end = s->channels;
    if (base < 0 || base >= end)
        return;
    memset(&s->pwm[base], 0, (size_t)(end - base) * sizeof s->pwm[0]);
    memset(&s->dout[base], 0, (size_t)(end - base) * sizeof s->dout[0]);
    for (int ch = base; ch < end; ch++) {
        const double a = motor_angle(s, ch);
        s->enc_zero[ch] = isnan(a) ? 0.0 : a;
    }
}

static void mirror(struct sim_board *s)
{
    struct xrf_sim_outputs *o = s->outputs;
    if (!o)
        return;
    int off = forced_off(s);
    /* Bounded by the arrays too: the count is checked at open, but the compiler cannot see it. */
    const int n = s->channels < XRF_MAX_CHANNELS ? s->channels : XRF_MAX_CHANNELS;
    for (int ch = 0; ch < n; ch++) {
        o->pwm[ch] = off ? 0 : s->pwm[ch];
        o->dout[ch] = (uint8_t)dout_now(s, ch);
    }
    s->ops->state(s->plant, o->plant, (int)(sizeof o->plant / sizeof o->plant[0]));
    __atomic_store_n(&o->active, 1u, __ATOMIC_RELEASE);
    if (s->snapshot && s->ops->save) {
        /* For the safety watcher's `hold` (plant.h): what it steps on from if the loop dies. */
        struct xrf_sim_snapshot *sn = s->snapshot;
        uint32_t seq = __atomic_load_n(&sn->seq, __ATOMIC_RELAXED);
        __atomic_store_n(&sn->seq, seq | 1u, __ATOMIC_RELAXED);
        __atomic_thread_fence(__ATOMIC_RELEASE);
        int n = s->ops->save(s->plant, sn->v, XRF_SIM_SNAPSHOT_MAX);
        sn->n = (uint32_t)n;
        __atomic_store_n(&sn->seq, (seq | 1u) + 1u, __ATOMIC_RELEASE);
    }
}

static void busy_wait_until(const struct timespec *start, uint32_t us)
{
    /* Spinning on the vDSO clock holds the caller for the whole transfer like a slow wire would,
     * without a system call that could demote an EVL thread. */
    struct timespec now;
    do
        clock_gettime(CLOCK_MONOTONIC, &now);
    while (ts_diff(&now, start) * 1e6 < (double)us);
}

/* Following a loop's board (xrf_sim_follow): its plant state and outputs taken over as they are
 * now. The seqlock gets a bounded number of tries (a killed loop may leave it odd for ever). */
static void follow_take(struct sim_board *s)
{
    const struct xrf_shm *src = s->follow;
    /* seq 0: the loop's board has not written a snapshot yet (not open): the arm is where this
     * board's plant started, parked. */
    if (__atomic_load_n(&src->sim_snapshot.seq, __ATOMIC_ACQUIRE) != 0 && s->ops->load != NULL &&
        s->ops->snapshot_len > 0 && s->ops->snapshot_len <= XRF_SIM_SNAPSHOT_MAX) {
        const int n = s->ops->snapshot_len;
        double v[XRF_SIM_SNAPSHOT_MAX];
        for (int tries = 0; tries < 1000; tries++) {
            uint32_t a = __atomic_load_n(&src->sim_snapshot.seq, __ATOMIC_ACQUIRE);
            memcpy(v, (const void *)src->sim_snapshot.v, (size_t)n * sizeof v[0]);
            __atomic_thread_fence(__ATOMIC_ACQUIRE);
            if ((a & 1u) == 0 && __atomic_load_n(&src->sim_snapshot.seq, __ATOMIC_RELAXED) == a)
                break;
        }
        s->ops->load(s->plant, v, n);
    }
    for (int ch = 0; ch < s->channels; ch++)
        s->pwm[ch] = __atomic_load_n(&src->sim.pwm[ch], __ATOMIC_RELAXED);
}

/* One frame with board `board` (its channels base .. base + 3). Only board 0's transfer moves the
 * plant on: a cycle that exchanges frames with several boards advances it once. */
static inline int sim_xfer_on(struct sim_board *s, int board, const uint8_t tx[XRF_ICO_FRAME],
                              uint8_t rx[XRF_ICO_FRAME])
{
    const int base = board * XRF_ICO_CHANNELS;
    struct timespec now;
    if (s->clock) {
        const int64_t ns = s->clock();
        now.tv_sec = (time_t)(ns / 1000000000LL);
        now.tv_nsec = (long)(ns % 1000000000LL);
    } else {
        clock_gettime(CLOCK_MONOTONIC, &now);
    }

    /* The outputs set by the previous frame acted until now; this frame's take over after. */
    double dt;
    if (s->fixed_dt > 0.0) {
        dt = s->fixed_dt;
    } else {
        const double max_gap = s->clock ? SIM_MAX_GAP_VIRTUAL_S : SIM_MAX_GAP_S;
        dt = s->have_last ? ts_diff(&now, &s->last) : 0.0;
        if (dt > max_gap)
            dt = max_gap;
    }
    const uint32_t resets = __atomic_exchange_n(&s->inject_reset, 0u, __ATOMIC_ACQ_REL);
    for (int b = 0; b < XRF_MAX_BOARDS; b++)
        if (resets & (1u << b))
            reset_board(s, b * XRF_ICO_CHANNELS);
    if (s->follow != NULL) {
        /* The loop drives the arm: its state is taken whenever its board wrote a new one; in
         * between (a loop that missed cycles, or is gone) the arm moves on by the loop's last
         * outputs, as the FPGA keeps driving them: the arm stays continuous, as a real one. */
        const uint32_t seq = __atomic_load_n(&s->follow->sim_snapshot.seq, __ATOMIC_ACQUIRE);
        if (seq != s->follow_seq) {
            follow_take(s);
            s->follow_seq = seq;
        } else if (board == 0) {
            advance(s, dt);
        }
        s->last = now;
        s->have_last = 1;
        const uint8_t op = tx[0];
        if (op == XRF_ICO_ALL || op == XRF_ICO_RESET ||
            (op >= XRF_ICO_PWM_1 && op < XRF_ICO_PWM_1 + XRF_ICO_CHANNELS))
            s->follow = NULL; /* someone else drives it now: the board steps on by itself */
    } else if (board == 0) {
        s->last = now;
        s->have_last = 1;
        advance(s, dt);
    }

    /* Copy first: tx and rx may be the same buffer. */
    uint8_t in[XRF_ICO_FRAME];
    memcpy(in, tx, XRF_ICO_FRAME);
    memset(rx, 0, XRF_ICO_FRAME);
    if (board > 0 && (s->faults.absent_board >> board) & 1u)
        return 0; /* nothing there: MISO reads zeros, no register takes the frame */

    uint8_t op = in[0];
    switch (op) {
    case XRF_ICO_INIT:
        if (!s->faults.no_init_reply)
            rx[XRF_ICO_INIT_REPLY_BYTE] = XRF_ICO_INIT_REPLY;
        break;
    case XRF_ICO_RESET:
        reset_board(s, base);
        break;
    case XRF_ICO_ALL:
        /* Inputs are latched before the new outputs apply, so a loopback shows last frame's
         * output, as on the FPGA where the reply is shifted out while the frame comes in. */
        for (int ch = 0; ch < XRF_ICO_CHANNELS; ch++)
            put_le16(&rx[1 + 2 * ch], in_word(s, base + ch));
        for (int ch = 0; ch < XRF_ICO_CHANNELS; ch++) {
            uint16_t w = (uint16_t)(in[2 + 2 * ch] | (in[3 + 2 * ch] << 8));
            s->pwm[base + ch] = word_pwm(w);
            s->dout[base + ch] = (w & 0x8000u) ? 1 : 0;
        }
        break;
    case XRF_ICO_PWM_1:
    case XRF_ICO_PWM_1 + 1:
    case XRF_ICO_PWM_1 + 2:
    case XRF_ICO_PWM_1 + 3: {
        /* The same word as in ALL: duty, direction and the channel's digital output. */
        uint16_t w = (uint16_t)(in[2] | (in[3] << 8));
        s->pwm[base + op - XRF_ICO_PWM_1] = word_pwm(w);
        s->dout[base + op - XRF_ICO_PWM_1] = (w & 0x8000u) ? 1 : 0;
        break;
    }
    case XRF_ICO_ENC_1:
    case XRF_ICO_ENC_1 + 1:
    case XRF_ICO_ENC_1 + 2:
    case XRF_ICO_ENC_1 + 3:
        put_le16(&rx[1], encoder(s, base + op - XRF_ICO_ENC_1));
        break;
    case XRF_ICO_TEST: {
        uint8_t pattern[XRF_ICO_FRAME];
        xrf_ico_test_pattern(pattern);
        memcpy(&rx[1], &pattern[1], XRF_ICO_FRAME - 1);
        rx[0] = 0;
        if (s->faults.corrupt_echo) {
            /* A few scattered bits, as a marginal clock or a bad ground would flip them. */
            rx[2] ^= 0x10;
            rx[7] ^= 0x01;
            rx[11] ^= 0x80;
        }
        break;
    }
    default: /* NOOP and unknown opcodes: the FPGA shifts out zeros */
        break;
    }

    mirror(s);
    if (s->faults.slow_link_us) {
        /* The wire is slow in real time (in simulated time the loop's clock runs on with it). */
        struct timespec start = now;
        if (s->clock)
            clock_gettime(CLOCK_MONOTONIC, &start);
        busy_wait_until(&start, s->faults.slow_link_us);
    }
    if (s->faults.stall_ms && ++s->transfers % SIM_STALL_EVERY == 0) {
        /* The caller is held as a busy machine holds it; the plant lives through the gap on
         * the outputs it has (the next transfer's dt), as a real one does. */
        struct timespec hold = {.tv_sec = s->faults.stall_ms / 1000,
                                .tv_nsec = (long)(s->faults.stall_ms % 1000) * 1000000L};
        nanosleep(&hold, NULL);
    }
    return 0;
}

static int sim_xfer(struct xrf_ico_transport *t, const uint8_t tx[XRF_ICO_FRAME],
                    uint8_t rx[XRF_ICO_FRAME])
{
    return sim_xfer_on((struct sim_board *)t, 0, tx, rx);
}

static int sim_xfer_board(struct xrf_ico_transport *t, int board, const uint8_t tx[XRF_ICO_FRAME],
                          uint8_t rx[XRF_ICO_FRAME])
{
    if (board < 0 || board >= t->boards)
        return -EINVAL;
    return sim_xfer_on((struct sim_board *)t, board, tx, rx);
}

static void sim_close(struct xrf_ico_transport *t)
{
    struct sim_board *s = (struct sim_board *)t;
    if (!s)
        return;
    if (s->outputs)
        __atomic_store_n(&s->outputs->active, 0u, __ATOMIC_RELEASE);
    free(s);
}

int xrf_sim_open(int robot, const struct xrf_sim_faults *faults, double fixed_dt_s,
                 struct xrf_sim_outputs *outputs, struct xrf_ico_transport **out)
{
    return xrf_sim_open_bench(robot, 0, faults, fixed_dt_s, outputs, out);
}

int xrf_sim_open_bench(int robot, int channels, const struct xrf_sim_faults *faults,
                       double fixed_dt_s, struct xrf_sim_outputs *outputs,
                       struct xrf_ico_transport **out)
{
    if (!out)
        return -EINVAL;
    *out = NULL;
    const struct xrf_plant_ops *ops = xrf_plant_ops(robot);
    const int need = xrf_plant_channels(robot);
    if (!ops || channels < 0 || channels > XRF_MAX_CHANNELS || (channels && channels < need))
        return -EINVAL;
    struct sim_board *s = calloc(1, sizeof *s + ops->size);
    if (!s)
        return -ENOMEM;
    s->ops = ops;
    s->channels = channels ? channels : need;
    ops->init(s->plant);
    if (faults)
        s->faults = *faults;
    if (s->faults.start_seed && ops->start)
        ops->start(s->plant, s->faults.start_seed);
    s->fixed_dt = fixed_dt_s > 0.0 ? fixed_dt_s : 0.0;
    s->outputs = outputs;
    for (int b = 0; b * XRF_ICO_CHANNELS < s->channels; b++)
        reset_board(s, b * XRF_ICO_CHANNELS);
    s->t.name = "sim";
    s->t.xfer = sim_xfer;
    s->t.boards = (s->channels + XRF_ICO_CHANNELS - 1) / XRF_ICO_CHANNELS;
    s->t.xfer_board = sim_xfer_board;
    s->t.close = sim_close;
    mirror(s);
    *out = &s->t;
    return 0;
}

int xrf_sim_set_clock(struct xrf_ico_transport *t, int64_t (*now_ns)(void))
{
    if (!t || t->xfer != sim_xfer)
        return -EINVAL;
    ((struct sim_board *)t)->clock = now_ns;
    return 0;
}

int xrf_sim_set_snapshot(struct xrf_ico_transport *t, struct xrf_sim_snapshot *snapshot)
{
    if (!t || t->xfer != sim_xfer)
        return -EINVAL;
    struct sim_board *s = (struct sim_board *)t;
    s->snapshot = snapshot;
    mirror(s);
    return 0;
}

int xrf_sim_follow(struct xrf_ico_transport *t, const struct xrf_shm *loop_shm)
{
    if (!t || t->xfer != sim_xfer)
        return -EINVAL;
    ((struct sim_board *)t)->follow = loop_shm;
    return 0;
}

int xrf_sim_inject_reset(struct xrf_ico_transport *t, int board)
{
    if (!t || t->xfer != sim_xfer || board < 0 || board >= t->boards)
        return -EINVAL;
    __atomic_fetch_or(&((struct sim_board *)t)->inject_reset, 1u << board, __ATOMIC_ACQ_REL);
    return 0;
}

int xrf_sim_robot_from_name(const char *name)
{
    return xrf_plant_id(name);
}

int xrf_sim_plant_state(struct xrf_ico_transport *t, double *state, int n)
{
    if (!t || t->xfer != sim_xfer || (!state && n > 0) || n < 0)
        return -EINVAL;
    const struct sim_board *s = (const struct sim_board *)t;
    return s->ops->state(s->plant, state, n);
}

/* --- fault spec ------------------------------------------------------------------------- */

/* Parses a whole decimal number in [lo, hi] from [p, end). */
static int parse_uint(const char *p, const char *end, unsigned long lo, unsigned long hi,
                      unsigned long *v)
{
    if (p == end)
        return -EINVAL;
    unsigned long x = 0;
    for (; p < end; p++) {
        if (*p < '0' || *p > '9')
            return -EINVAL;
        x = x * 10 + (unsigned long)(*p - '0');
        if (x > hi)
            return -EINVAL;
    }
    if (x < lo)
        return -EINVAL;
    *v = x;
    return 0;
}

static int key_is(const char *k, size_t klen, const char *name)
{
    return strlen(name) == klen && strncmp(k, name, klen) == 0;
}

static int parse_item(const char *p, const char *end, struct xrf_sim_faults *f)
{
    const char *eq = memchr(p, '=', (size_t)(end - p));
    const char *k = p;
    size_t klen = (size_t)((eq ? eq : end) - p);
    const char *v = eq ? eq + 1 : end;
    unsigned long x, y;

    if (key_is(k, klen, "no_init") || key_is(k, klen, "no_init_reply") ||
        key_is(k, klen, "corrupt_echo")) {
        int on = 1;
        if (eq) {
            if (parse_uint(v, end, 0, 1, &x))
                return -EINVAL;
            on = (int)x;
        }
        if (key_is(k, klen, "corrupt_echo"))
            f->corrupt_echo = on;
        else
            f->no_init_reply = on;
        return 0;
    }
    if (!eq)
        return -EINVAL;
    if (key_is(k, klen, "dead_encoder") || key_is(k, klen, "reversed_motor") ||
        key_is(k, klen, "loopback")) {
        if (parse_uint(v, end, 1, 4, &x))
            return -EINVAL;
        uint8_t bit = (uint8_t)(1u << (x - 1));
        if (key_is(k, klen, "dead_encoder"))
            f->dead_encoder |= bit;
        else if (key_is(k, klen, "reversed_motor"))
            f->reversed_motor |= bit;
        else
            f->loopback |= bit;
        return 0;
    }
    if (key_is(k, klen, "absent_board")) {
        /* board 1 carries every loop's IcoIo: only a further board can be missing */
        if (parse_uint(v, end, 2, XRF_MAX_BOARDS, &x))
            return -EINVAL;
        f->absent_board |= (uint8_t)(1u << (x - 1));
        return 0;
    }
    if (key_is(k, klen, "stuck_input")) {
        const char *colon = memchr(v, ':', (size_t)(end - v));
        if (!colon || parse_uint(v, colon, 1, 8, &x) || parse_uint(colon + 1, end, 0, 1, &y))
            return -EINVAL;
        uint8_t bit = (uint8_t)(1u << (x - 1));
        f->stuck_input |= bit;
        if (y)
            f->stuck_value |= bit;
        else
            f->stuck_value &= (uint8_t)~bit;
        return 0;
    }
    if (key_is(k, klen, "start")) {
        if (parse_uint(v, end, 1, 4294967295ul, &x))
            return -EINVAL;
        f->start_seed = (uint32_t)x;
        return 0;
    }
    if (key_is(k, klen, "stall_ms")) {
        if (parse_uint(v, end, 1, 10000, &x))
            return -EINVAL;
        f->stall_ms = (uint32_t)x;
        return 0;
    }
    if (key_is(k, klen, "slow_link_us")) {
        if (parse_uint(v, end, 0, 10000000, &x))
            return -EINVAL;
        f->slow_link_us = (uint32_t)x;
        return 0;
    }
    return -EINVAL;
}

int xrf_sim_parse_faults(const char *spec, struct xrf_sim_faults *faults)
{
    if (!faults)
        return -EINVAL;
    memset(faults, 0, sizeof *faults);
    if (!spec)
        return 0;
    const char *p = spec;
    while (*p) {
        const char *end = strchr(p, ',');
        if (!end)
            end = p + strlen(p);
        /* Spaces around items are a typing convenience, not part of a name. */
        const char *a = p, *b = end;
        while (a < b && (*a == ' ' || *a == '\t'))
            a++;
        while (b > a && (b[-1] == ' ' || b[-1] == '\t'))
            b--;
        if (a < b && parse_item(a, b, faults) != 0) {
            memset(faults, 0, sizeof *faults);
            return -EINVAL;
        }
        p = *end ? end + 1 : end;
    }
    return 0;
}
