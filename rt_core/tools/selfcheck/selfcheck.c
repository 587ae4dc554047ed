/*
 * selfcheck.c — the bench self-check's steps (selfcheck.h, docs/educators/selfcheck.md), part of
 * the xrf-selfcheck tool only: the runtime library a controller links has none of it.
 *
 * Every frame goes through the loop's own transport and frame builders (ico.c). Pulses are
 * driven with ALL frames in a timed loop (clock_nanosleep on an absolute grid) and the encoders
 * are read from the ALL replies and unwrapped (14 bits). The abort flag is checked between
 * frames; whatever ends the run, the outputs are zeroed (RESET, then ALL with zeros).
 */
#define _POSIX_C_SOURCE 200809L

#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include "selfcheck.h"
#include "xrf/plants.h"
#include "xrf/sim.h"

/* ---- small helpers ------------------------------------------------------------------------- */

const char *xrf_selfcheck_status_name(int status)
{
    switch (status) {
    case XRF_SC_PASS:
        return "pass";
    case XRF_SC_WARN:
        return "warn";
    case XRF_SC_FAIL:
        return "fail";
    default:
        return "skipped";
    }
}

char *xrf_selfcheck_json_string(const char *s, char *buf, size_t len)
{
    size_t o = 0;
    if (len < 3) {
        if (len)
            buf[0] = 0;
        return buf;
    }
    buf[o++] = '"';
    for (const unsigned char *p = (const unsigned char *)(s ? s : ""); *p; p++) {
        char tmp[8];
        const char *e = NULL;
        switch (*p) {
        case '"':
            e = "\\\"";
            break;
        case '\\':
            e = "\\\\";
            break;
        case '\n':
            e = "\\n";
            break;
        case '\r':
            e = "\\r";
            break;
        case '\t':
            e = "\\t";
            break;
        default:
            if (*p < 0x20) {
                snprintf(tmp, sizeof tmp, "\\u%04x", *p);
                e = tmp;
            }
        }
        size_t n = e ? strlen(e) : 1;
        if (o + n + 2 > len)
            break;
        if (e) {
            memcpy(buf + o, e, n);
            o += n;
        } else {
            buf[o++] = (char)*p;
        }
    }
    buf[o++] = '"';
    buf[o] = 0;
    return buf;
}

static void set_text(char *dst, size_t len, const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(dst, len, fmt, ap);
    va_end(ap);
}

#define SETF(field, ...) set_text((field), sizeof(field), __VA_ARGS__)

static void result_init(struct xrf_selfcheck_result *r, const char *id, int channel,
                        const char *title)
{
    memset(r, 0, sizeof *r);
    SETF(r->id, "%s", id);
    r->channel = channel;
    r->status = XRF_SC_SKIP;
    SETF(r->title, "%s", title);
    SETF(r->data, "{}");
}

/* ---- profile ------------------------------------------------------------------------------- */

void xrf_selfcheck_profile_defaults(struct xrf_selfcheck_profile *p)
{
    memset(p, 0, sizeof *p);
    SETF(p->name, "default");
    p->pwm_limit = XRF_SC_MAX_DUTY;
    p->period_us = 1000;
    p->settle_ms = 150;
    p->reset_tolerance = 2;
    p->echo_frames = 1000;
    p->timing_frames = 1000;
    p->warn_median_us = 60.0;
    p->fail_median_us = 150.0;
    p->warn_max_us = 500.0;
    for (int i = 0; i < XRF_MAX_CHANNELS; i++) {
        struct xrf_sc_channel *c = &p->ch[i];
        SETF(c->name, "channel %d", i + 1);
        if (i < XRF_ICO_CHANNELS)
            SETF(c->connector, "PMOD %d", i + 1);
        else
            SETF(c->connector, "board %d PMOD %d", i / XRF_ICO_CHANNELS + 1,
                 i % XRF_ICO_CHANNELS + 1);
        c->direction = 1;
        c->first_pulse = 1;
        c->duty = 0.1;
        c->duration_ms = 100;
        c->min_counts = 50;
        c->din_idle[0] = c->din_idle[1] = -1;
        SETF(c->pin_name[0], "pin 1");
        SETF(c->pin_name[1], "pin 2");
    }
}

/* ---- opening (the "spi" step) -------------------------------------------------------------- */

int xrf_selfcheck_open(const struct xrf_selfcheck_target *tg, struct xrf_ico_transport **out,
                       struct xrf_selfcheck_result *r)
{
    result_init(r, "spi", 0, "SPI link opened and configured");
    if (out)
        *out = NULL;
    if (!tg || !out || !tg->transport) {
        r->status = XRF_SC_FAIL;
        SETF(r->message, "no transport given");
        return -EINVAL;
    }
    const char *dev = tg->device && tg->device[0] ? tg->device : "/dev/spidev0.0";
    uint32_t speed = tg->speed_hz ? tg->speed_hz : 31000000u;
    int rc;
    char js[160];
    if (strcmp(tg->transport, "sim") == 0) {
        struct xrf_sim_faults f;
        int robot = xrf_sim_robot_from_name(tg->sim ? tg->sim : "relbot");
        if (robot < 0) {
            r->status = XRF_SC_FAIL;
            char names[128];
            xrf_plant_names(names, sizeof names);
            SETF(r->message, "unknown simulated robot '%s' (the plant table has: %s)", tg->sim,
                 names);
            return -EINVAL;
        }
        if (xrf_sim_parse_faults(tg->faults, &f) != 0) {
            r->status = XRF_SC_FAIL;
            SETF(r->message, "'%s' is not a valid fault list", tg->faults ? tg->faults : "");
            SETF(r->action, "see docs/rt_core/simulator.md, section Faults");
            return -EINVAL;
        }
        rc = xrf_sim_open(robot, &f, 0.0, tg->sim_outputs, out);
        if (rc == 0) {
            r->status = XRF_SC_PASS;
            SETF(r->message, "simulated %s board opened (no SPI wire)",
                 tg->sim ? tg->sim : "relbot");
            SETF(r->data, "{\"transport\":\"sim\",\"sim\":%s}",
                 xrf_selfcheck_json_string(tg->sim ? tg->sim : "relbot", js, sizeof js));
            return 0;
        }
    } else if (strcmp(tg->transport, "spidev") == 0) {
        rc = xrf_spidev_open(dev, speed, out);
    } else if (strcmp(tg->transport, "evl-spidev") == 0) {
        rc = xrf_evl_spidev_open(dev, speed, out);
    } else {
        r->status = XRF_SC_FAIL;
        SETF(r->message, "unknown transport '%s' (use sim, spidev or evl-spidev)", tg->transport);
        return -EINVAL;
    }
    SETF(r->data, "{\"transport\":\"%s\",\"device\":%s,\"speed_hz\":%u}", tg->transport,
         xrf_selfcheck_json_string(dev, js, sizeof js), speed);
    if (rc == 0) {
        r->status = XRF_SC_PASS;
        SETF(r->message, "%s opened: SPI mode 0, 8 bits per word, %.1f MHz", dev, speed / 1e6);
        return 0;
    }
    r->status = XRF_SC_FAIL;
    switch (-rc) {
    case ENOENT:
        SETF(r->message, "%s does not exist: the SPI interface is not enabled", dev);
        SETF(r->action, "enable SPI (dtparam=spi=on in /boot/firmware/config.txt) and reboot");
        break;
    case EACCES:
    case EPERM:
        SETF(r->message, "no permission to open %s", dev);
        SETF(r->action, "run the check as a user in the 'spi' group (or as the appliance)");
        break;
    case EBUSY:
        SETF(r->message, "%s is busy: another program holds the SPI bus", dev);
        SETF(r->action, "stop the running loop (or other SPI program) and run the check again");
        break;
    case ENOSYS:
        SETF(r->message, "the %s transport is not built into this rt_core (no libevl)",
             tg->transport);
        SETF(r->action, "use --transport spidev, or build rt_core on the EVL kernel image");
        break;
    default:
        SETF(r->message, "%s cannot be opened or configured (mode 0, 8 bits, %.1f MHz): %s", dev,
             speed / 1e6, strerror(-rc));
        SETF(r->action, "check that the SPI driver is loaded and supports this speed");
    }
    return rc;
}

/* ---- running ------------------------------------------------------------------------------- */

struct sc {
    struct xrf_ico_transport *t;
    const struct xrf_selfcheck_profile *p;
    const struct xrf_selfcheck_hooks *h;
    struct xrf_selfcheck_summary *sum;
    int16_t pwm_max;
    struct timespec next;
    int nch;                           /* the bench's channels checked: 1..XRF_MAX_CHANNELS */
    int boards;                        /* ico boards carrying them */
    int board_ok[XRF_MAX_BOARDS];      /* 1: answered INIT (board 0: the "init" step) */
    int32_t raw[XRF_MAX_CHANNELS];     /* counter of the latest reply per channel */
    int32_t last[XRF_MAX_CHANNELS];    /* the one before, for unwrapping */
    int64_t pos[XRF_MAX_CHANNELS];     /* unwrapped */
    uint8_t din[2 * XRF_MAX_CHANNELS]; /* channel c pin k at 2c + k, as in xrf_ico_in */
    int have_raw;
    int xfer_err;
    unsigned char done[64]; /* planned step i reported */
};

/* The steps after "spi", in the order they run: "init", "board.B" for B = 2..boards, "echo",
 * "reset", "motor.N", "dout.N", "din.N" for N = 1..nch, "timing" (ids built, not a table: the
 * count follows the bench). Returns the number of planned steps; writes step i's id. */
static int planned_id(const struct sc *s, int i, char *id, size_t len)
{
    int nb = s->boards - 1, n = s->nch;
    int total = 4 + nb + 3 * n;
    if (i < 0 || i >= total)
        return total;
    if (i == 0)
        snprintf(id, len, "init");
    else if (i <= nb)
        snprintf(id, len, "board.%d", i + 1);
    else if (i == nb + 1)
        snprintf(id, len, "echo");
    else if (i == nb + 2)
        snprintf(id, len, "reset");
    else if (i < nb + 3 + n)
        snprintf(id, len, "motor.%d", i - nb - 2);
    else if (i < nb + 3 + 2 * n)
        snprintf(id, len, "dout.%d", i - nb - 2 - n);
    else if (i < nb + 3 + 3 * n)
        snprintf(id, len, "din.%d", i - nb - 2 - 2 * n);
    else
        snprintf(id, len, "timing");
    return total;
}

/* The channel of an id "motor.N" / "dout.N" / "din.N" (N >= 1), else 0. */
static int id_channel(const char *id)
{
    if (strncmp(id, "board.", 6) == 0)
        return 0;
    const char *dot = strchr(id, '.');
    return dot ? atoi(dot + 1) : 0;
}

static void planned_title(const struct sc *s, const char *id, char *buf, size_t len)
{
    int ch = id_channel(id);
    if (strncmp(id, "motor.", 6) == 0)
        snprintf(buf, len, "channel %d (%s): motor and encoder", ch, s->p->ch[ch - 1].name);
    else if (strncmp(id, "dout.", 5) == 0)
        snprintf(buf, len, "channel %d: digital output read back", ch);
    else if (strncmp(id, "din.", 4) == 0)
        snprintf(buf, len, "channel %d: digital inputs", ch);
    else if (strcmp(id, "echo") == 0)
        snprintf(buf, len, "SPI link integrity (TEST echo)");
    else if (strcmp(id, "reset") == 0)
        snprintf(buf, len, "RESET: encoders read zero, outputs off");
    else if (strcmp(id, "timing") == 0)
        snprintf(buf, len, "SPI link timing");
    else if (strncmp(id, "board.", 6) == 0)
        snprintf(buf, len, "ico board %d present (INIT answered)", atoi(id + 6));
    else
        snprintf(buf, len, "ico board present (INIT answered)");
}

static int aborted(const struct sc *s)
{
    return s->h && s->h->abort_flag && *s->h->abort_flag;
}

static void emit(struct sc *s, const struct xrf_selfcheck_result *r)
{
    switch (r->status) {
    case XRF_SC_PASS:
        s->sum->passed++;
        break;
    case XRF_SC_WARN:
        s->sum->warned++;
        break;
    case XRF_SC_FAIL:
        s->sum->failed++;
        break;
    default:
        s->sum->skipped++;
    }
    int total = planned_id(s, -1, NULL, 0);
    for (int i = 0; i < total && i < (int)sizeof s->done; i++) {
        char id[24];
        planned_id(s, i, id, sizeof id);
        if (strcmp(id, r->id) == 0)
            s->done[i] = 1;
    }
    if (s->h && s->h->result)
        s->h->result(s->h->user, r);
}

static void progress(struct sc *s, const char *id, int ch, double frac, const char *fmt, ...)
{
    if (!s->h || !s->h->progress)
        return;
    char text[XRF_SC_TEXT];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(text, sizeof text, fmt, ap);
    va_end(ap);
    s->h->progress(s->h->user, id, ch, text, frac);
}

static void skip(struct sc *s, const char *id, int ch, const char *title, const char *why)
{
    struct xrf_selfcheck_result r;
    result_init(&r, id, ch, title);
    r.status = XRF_SC_SKIP;
    SETF(r.message, "%s", why);
    emit(s, &r);
}

static int xfer_b(struct sc *s, int board, const uint8_t tx[XRF_ICO_FRAME],
                  uint8_t rx[XRF_ICO_FRAME])
{
    int rc = board == 0 ? s->t->xfer(s->t, tx, rx) : s->t->xfer_board(s->t, board, tx, rx);
    if (rc && !s->xfer_err)
        s->xfer_err = rc;
    return rc;
}

static int xfer(struct sc *s, const uint8_t tx[XRF_ICO_FRAME], uint8_t rx[XRF_ICO_FRAME])
{
    return xfer_b(s, 0, tx, rx);
}

static int op_b(struct sc *s, int board, uint8_t opcode, uint8_t rx[XRF_ICO_FRAME])
{
    uint8_t tx[XRF_ICO_FRAME];
    xrf_ico_frame_op(opcode, tx);
    return xfer_b(s, board, tx, rx);
}

static int op(struct sc *s, uint8_t opcode, uint8_t rx[XRF_ICO_FRAME])
{
    uint8_t tx[XRF_ICO_FRAME];
    xrf_ico_frame_op(opcode, tx);
    return xfer(s, tx, rx);
}

static void clock_start(struct sc *s)
{
    clock_gettime(CLOCK_MONOTONIC, &s->next);
}

/* Waits for the next slot of the frame grid. Returns non-zero when aborted. */
static int tick(struct sc *s)
{
    long period_ns = (long)s->p->period_us * 1000L;
    s->next.tv_nsec += period_ns;
    while (s->next.tv_nsec >= 1000000000L) {
        s->next.tv_nsec -= 1000000000L;
        s->next.tv_sec++;
    }
    struct timespec now;
    clock_gettime(CLOCK_MONOTONIC, &now);
    double late =
        (double)(now.tv_sec - s->next.tv_sec) * 1e9 + (double)(now.tv_nsec - s->next.tv_nsec);
    if (late > (double)period_ns) {
        s->next = now; /* fell behind (slow link, preemption): re-anchor, never burst */
    } else {
        while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &s->next, NULL) == EINTR)
            if (aborted(s))
                return 1;
    }
    return aborted(s);
}

/* The outputs of every channel of the bench for one frame. */
struct sc_out {
    int16_t pwm[XRF_MAX_CHANNELS];
    uint8_t dout[XRF_MAX_CHANNELS];
};

/* One ALL frame with every board that answered, the others first and board 0 last, as the loop
 * does (XRF2's further boards): a simulated plant steps once, at board 0's transfer, with all
 * outputs set. The replies' counters are unwrapped into s->pos, the inputs copied to s->din. */
static int frame_all(struct sc *s, const struct sc_out *o)
{
    for (int b = s->boards - 1; b >= 0; b--) {
        if (!s->board_ok[b])
            continue;
        uint8_t tx[XRF_ICO_FRAME], rx[XRF_ICO_FRAME];
        struct xrf_ico_out out;
        struct xrf_ico_in in;
        memcpy(out.pwm, &o->pwm[b * XRF_ICO_CHANNELS], sizeof out.pwm);
        memcpy(out.dout, &o->dout[b * XRF_ICO_CHANNELS], sizeof out.dout);
        xrf_ico_encode_all(&out, s->pwm_max, tx);
        int rc = xfer_b(s, b, tx, rx);
        if (rc)
            return rc;
        xrf_ico_decode_all(rx, &in);
        for (int k = 0; k < XRF_ICO_CHANNELS; k++) {
            s->raw[b * XRF_ICO_CHANNELS + k] = in.enc[k];
            s->din[2 * (b * XRF_ICO_CHANNELS + k)] = in.din[2 * k];
            s->din[2 * (b * XRF_ICO_CHANNELS + k) + 1] = in.din[2 * k + 1];
        }
    }
    for (int i = 0; i < s->nch; i++) {
        int32_t v = s->raw[i];
        if (s->have_raw) {
            int32_t d = (v - s->last[i]) & (XRF_ICO_ENC_MODULO - 1);
            if (d >= XRF_ICO_ENC_MODULO / 2)
                d -= XRF_ICO_ENC_MODULO;
            s->pos[i] += d;
        } else {
            s->pos[i] = v >= XRF_ICO_ENC_MODULO / 2 ? v - XRF_ICO_ENC_MODULO : v;
        }
        s->last[i] = v;
    }
    s->have_raw = 1;
    return 0;
}

static const struct sc_out zero_out;

/* One board's RESET + zero ALL (twice). */
static int zero_board(struct xrf_ico_transport *t, int b)
{
    uint8_t tx[XRF_ICO_FRAME], rx[XRF_ICO_FRAME];
    static const struct xrf_ico_out zero;
    int first = 0, rc;
    xrf_ico_frame_op(XRF_ICO_RESET, tx);
    for (int i = 0; i < 3; i++) {
        rc = b == 0 ? t->xfer(t, tx, rx) : t->xfer_board(t, b, tx, rx);
        if (!first)
            first = rc;
        /* Twice zero ALL: a board that answers one frame late has certainly taken the zeros. */
        xrf_ico_encode_all(&zero, 0, tx);
    }
    return first;
}

int xrf_selfcheck_zero_outputs(struct xrf_ico_transport *t)
{
    if (!t)
        return -EINVAL;
    /* Every board, whether it answered INIT or not: zeros are safe to send anywhere. */
    int boards = t->xfer_board && t->boards > 1 ? t->boards : 1;
    if (boards > XRF_MAX_BOARDS)
        boards = XRF_MAX_BOARDS;
    int first = 0;
    for (int b = boards - 1; b >= 0; b--) {
        int rc = zero_board(t, b);
        if (!first)
            first = rc;
    }
    return first;
}

static void link_broken(struct sc *s, struct xrf_selfcheck_result *r)
{
    r->status = XRF_SC_FAIL;
    SETF(r->message, "an SPI transfer failed: %s", strerror(-s->xfer_err));
    SETF(r->action,
         "check the connection between the Pi and the ico board and run the check again");
}

/* -- INIT -- */
static int step_init(struct sc *s)
{
    struct xrf_selfcheck_result r;
    result_init(&r, "init", 0, "ico board present (INIT answered)");
    progress(s, "init", 0, 0.0, "asking the ico board to identify itself (INIT)");
    uint8_t rx[XRF_ICO_FRAME];
    int got = -1, ok = 0;
    for (int i = 0; i < 3 && !ok; i++) {
        if (op(s, XRF_ICO_INIT, rx)) {
            link_broken(s, &r);
            emit(s, &r);
            return -1;
        }
        got = rx[XRF_ICO_INIT_REPLY_BYTE];
        ok = got == XRF_ICO_INIT_REPLY;
    }
    SETF(r.data, "{\"reply_byte4\":%d,\"expected\":%d}", got, XRF_ICO_INIT_REPLY);
    if (ok) {
        r.status = XRF_SC_PASS;
        SETF(r.message, "the ico board answered INIT with %d: it is there", XRF_ICO_INIT_REPLY);
    } else {
        r.status = XRF_SC_FAIL;
        SETF(r.message,
             "the ico board did not answer INIT (byte 4 of the reply is %d, expected %d): no "
             "board is there, it has no power, or its FPGA is not programmed",
             got, XRF_ICO_INIT_REPLY);
        SETF(r.action,
             "check that the ico board sits on the Pi's header and is powered (LED on), and that "
             "its FPGA image is loaded; then run the check again");
    }
    emit(s, &r);
    return ok ? 0 : -1;
}

/* -- the further boards of a bench (2, 3): INIT each. One that does not answer fails its own
 * step, its channels are skipped with the reason, and the others are checked. -- */
static int step_boards(struct sc *s)
{
    for (int b = 1; b < s->boards; b++) {
        struct xrf_selfcheck_result r;
        char id[24], title[96];
        int lo = b * XRF_ICO_CHANNELS + 1;
        int hi = lo + XRF_ICO_CHANNELS - 1 < s->nch ? lo + XRF_ICO_CHANNELS - 1 : s->nch;
        char span[32]; /* "channels 5-8", or "channel 9" alone */
        if (hi > lo)
            snprintf(span, sizeof span, "channels %d-%d", lo, hi);
        else
            snprintf(span, sizeof span, "channel %d", lo);
        snprintf(id, sizeof id, "board.%d", b + 1);
        snprintf(title, sizeof title, "ico board %d present (INIT answered)", b + 1);
        result_init(&r, id, 0, title);
        progress(s, id, 0, 0.0, "asking ico board %d (%s) to identify itself", b + 1, span);
        uint8_t rx[XRF_ICO_FRAME];
        int got = -1, ok = 0;
        for (int i = 0; i < 3 && !ok; i++) {
            if (op_b(s, b, XRF_ICO_INIT, rx)) {
                link_broken(s, &r);
                emit(s, &r);
                return -1;
            }
            got = rx[XRF_ICO_INIT_REPLY_BYTE];
            ok = got == XRF_ICO_INIT_REPLY;
        }
        s->board_ok[b] = ok;
        SETF(r.data, "{\"board\":%d,\"channels\":[%d,%d],\"reply_byte4\":%d,\"expected\":%d}",
             b + 1, lo, hi, got, XRF_ICO_INIT_REPLY);
        if (ok) {
            r.status = XRF_SC_PASS;
            SETF(r.message, "ico board %d (%s) answered INIT with %d: it is there", b + 1, span,
                 XRF_ICO_INIT_REPLY);
            zero_board(s->t, b);
        } else {
            r.status = XRF_SC_FAIL;
            SETF(r.message,
                 "ico board %d (%s) did not answer INIT (byte 4 of the reply is %d, "
                 "expected %d): it is not there, has no power, or its FPGA is not programmed; "
                 "its channels are not checked",
                 b + 1, span, got, XRF_ICO_INIT_REPLY);
            SETF(r.action,
                 "check that ico board %d is stacked and powered (LED on) and its FPGA image is "
                 "loaded; then run the check again",
                 b + 1);
        }
        emit(s, &r);
    }
    return 0;
}

/* A channel on a board that did not answer: its steps are skipped with that reason. */
static int board_missing(struct sc *s, const char *id, int ch, const char *title)
{
    int b = ch / XRF_ICO_CHANNELS;
    if (s->board_ok[b])
        return 0;
    char why[128];
    snprintf(why, sizeof why,
             "not run: ico board %d, which carries channel %d, did not answer INIT", b + 1, ch + 1);
    skip(s, id, ch + 1, title, why);
    return 1;
}

/* A JSON array of the first n values. */
static void json_ints(char *buf, size_t len, const int64_t *v, int n)
{
    size_t o = 0;
    buf[0] = 0;
    for (int i = 0; i < n && o + 24 < len; i++)
        o += (size_t)snprintf(buf + o, len - o, "%s%lld", i ? "," : "[", (long long)v[i]);
    snprintf(buf + o, len - o, "%s]", n ? "" : "[");
}

/* -- TEST echo -- */
static int bit_errors_reversed(const uint8_t rx[XRF_ICO_FRAME])
{
    uint8_t rev[XRF_ICO_FRAME];
    for (int i = 0; i < XRF_ICO_FRAME; i++)
        rev[i] = xrf_ico_bitrev8(rx[i]);
    return xrf_ico_test_bit_errors(rev);
}

static int step_echo(struct sc *s)
{
    struct xrf_selfcheck_result r;
    result_init(&r, "echo", 0, "SPI link integrity (TEST echo)");
    int n = s->p->echo_frames;
    uint8_t tx[XRF_ICO_FRAME], rx[XRF_ICO_FRAME];
    xrf_ico_test_pattern(tx);
    /* One warm-up frame: a board that answers one frame late echoes this one next time. */
    if (xfer(s, tx, rx)) {
        link_broken(s, &r);
        emit(s, &r);
        return -1;
    }
    long bits = 0;
    int bad = 0, zero_replies = 0, reversed = 0, done = 0;
    for (int i = 0; i < n; i++) {
        if (aborted(s))
            return -EINTR;
        if (i % 100 == 0)
            progress(s, "echo", 0, (double)i / n, "TEST frame %d of %d", i, n);
        if (xfer(s, tx, rx)) {
            link_broken(s, &r);
            emit(s, &r);
            return -1;
        }
        done++;
        int e = xrf_ico_test_bit_errors(rx);
        if (e) {
            bad++;
            bits += e;
            int allzero = 1;
            for (int k = 1; k < XRF_ICO_FRAME; k++)
                allzero &= rx[k] == 0;
            zero_replies += allzero;
            reversed += bit_errors_reversed(rx) == 0;
        }
    }
    double ber = done ? (double)bits / (88.0 * done) : 0.0;
    SETF(r.data, "{\"frames\":%d,\"bad_frames\":%d,\"bit_errors\":%ld,\"bit_error_rate\":%.3g}",
         done, bad, bits, ber);
    if (bad == 0) {
        r.status = XRF_SC_PASS;
        SETF(r.message, "%d TEST frames came back exactly (0 bit errors in %ld bits)", done,
             88L * done);
    } else if (zero_replies == bad) {
        r.status = XRF_SC_FAIL;
        SETF(r.message,
             "the TEST echo came back as all zeros in %d of %d frames: nothing is "
             "sent back on the MISO line",
             bad, done);
        SETF(r.action, "check the SPI ribbon/wires between Pi and ico board (MISO) and the "
                       "board's power");
    } else if (reversed == bad) {
        r.status = XRF_SC_FAIL;
        SETF(r.message, "the TEST echo comes back bit-reversed: the transport does not match the "
                        "board's LSB-first bit order");
        SETF(r.action, "this is a software/transport problem, not the bench: report it to the "
                       "lab's developers");
    } else {
        r.status = XRF_SC_FAIL;
        SETF(r.message,
             "%ld bit errors in %d of %d TEST frames (bit error rate %.2g): the SPI "
             "link is unreliable",
             bits, bad, done, ber);
        SETF(r.action, "reseat the ico board and check the SPI wires and ground; a loose or long "
                       "cable at 31 MHz flips bits (try a lower SPI speed to confirm)");
    }
    emit(s, &r);
    return 0;
}

/* -- RESET -- */
static int step_reset(struct sc *s)
{
    struct xrf_selfcheck_result r;
    result_init(&r, "reset", 0, "RESET: encoders read zero, outputs off");
    progress(s, "reset", 0, 0.0, "RESET, then reading every encoder");
    uint8_t rx[XRF_ICO_FRAME];
    int64_t enc_after[XRF_MAX_CHANNELS] = {0};
    for (int b = 0; b < s->boards; b++)
        if (s->board_ok[b] && op_b(s, b, XRF_ICO_RESET, rx))
            goto broken;
    for (int ch = 0; ch < s->nch; ch++) {
        if (!s->board_ok[ch / XRF_ICO_CHANNELS])
            continue;
        if (op_b(s, ch / XRF_ICO_CHANNELS, (uint8_t)(XRF_ICO_ENC_1 + ch % XRF_ICO_CHANNELS), rx))
            goto broken;
        int32_t v = xrf_ico_decode_enc(rx);
        enc_after[ch] = v >= XRF_ICO_ENC_MODULO / 2 ? v - XRF_ICO_ENC_MODULO : v;
    }
    /* 50 ms with every output off: nothing may move. */
    s->have_raw = 0;
    clock_start(s);
    if (frame_all(s, &zero_out))
        goto broken;
    int64_t start[XRF_MAX_CHANNELS];
    memcpy(start, s->pos, sizeof start);
    int frames = 50000 / s->p->period_us + 1;
    for (int i = 0; i < frames; i++) {
        if (tick(s))
            return -EINTR;
        if (frame_all(s, &zero_out))
            goto broken;
    }
    int tol = s->p->reset_tolerance;
    int not_zero = 0, moving = 0;
    int64_t drift[XRF_MAX_CHANNELS] = {0};
    for (int ch = 0; ch < s->nch; ch++) {
        drift[ch] = s->pos[ch] - start[ch];
        if (llabs(enc_after[ch]) > tol && !not_zero)
            not_zero = ch + 1;
        if (llabs(drift[ch]) > tol && !moving)
            moving = ch + 1;
    }
    char after[XRF_MAX_CHANNELS * 24], moved[XRF_MAX_CHANNELS * 24];
    json_ints(after, sizeof after, enc_after, s->nch);
    json_ints(moved, sizeof moved, drift, s->nch);
    SETF(r.data, "{\"after_reset\":%s,\"drift_with_outputs_off\":%s,\"tolerance\":%d}", after,
         moved, tol);
    if (not_zero) {
        r.channel = not_zero;
        r.status = XRF_SC_FAIL;
        SETF(r.message,
             "encoder %d reads %lld right after RESET (expected 0): the board did not "
             "reset its counters",
             not_zero, (long long)enc_after[not_zero - 1]);
        SETF(r.action, "power-cycle the ico board and run the check again; if it stays, the FPGA "
                       "image on the board is wrong");
    } else if (moving) {
        r.channel = moving;
        r.status = XRF_SC_FAIL;
        SETF(r.message,
             "encoder %d moved %lld counts in 50 ms with every output off: something "
             "drives or turns that axis",
             moving, (long long)drift[moving - 1]);
        SETF(r.action,
             "keep hands off the robot during the check; if nobody touched it, the "
             "motor driver of %s does not switch off (or the encoder signal is noisy)",
             s->p->ch[moving - 1].connector);
    } else {
        r.status = XRF_SC_PASS;
        if (s->nch == 4)
            SETF(r.message,
                 "after RESET all four encoders read 0 and stay there with the outputs off");
        else
            SETF(r.message,
                 "after RESET all %d encoders read 0 and stay there with the outputs off", s->nch);
    }
    emit(s, &r);
    return 0;
broken:
    link_broken(s, &r);
    emit(s, &r);
    return -1;
}

/* -- motor pulses -- */
enum { P_OK, P_WEAK, P_NONE, P_WRONG, P_HIGH };
enum { MOTOR_ATTEMPTS = 3 };
#define MOTOR_GAP_MS \
    20.0 /* without a max_counts: the longest frame gap the counts are trusted over */

static int64_t mono_ns(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (int64_t)t.tv_sec * 1000000000LL + t.tv_nsec;
}

/* One pulse; *on_ms is how long the PWM was really on (first on-frame to first off-frame): a
 * loaded machine or a slow link stretches the frame grid, and the motor turns for as long as the
 * board holds the PWM, so the plausible count range follows the measured time, not the asked. */
/* *gap_ms is the longest time between two of its frames: the encoders are read as a counter
 * modulo XRF_ICO_ENC_MODULO, so a frame gap in which an axis moves half of that or more turns
 * the count into nonsense (CI, load ~9: a tilt pulsed negative "moved" +3209). */
static int pulse(struct sc *s, int ch, int16_t pwm, int ms, int64_t delta[XRF_MAX_CHANNELS],
                 double *on_ms, double *gap_ms, const char *what)
{
    struct sc_out out = zero_out;
    int64_t start[XRF_MAX_CHANNELS];
    memcpy(start, s->pos, sizeof start);
    int on = ms * 1000 / s->p->period_us;
    int settle = s->p->settle_ms * 1000 / s->p->period_us;
    char id[24]; /* "motor." + any int */
    snprintf(id, sizeof id, "motor.%d", ch + 1);
    progress(s, id, ch + 1, 0.0, "%s", what);
    int64_t t_on = 0, t_last = 0;
    *on_ms = ms;
    *gap_ms = 0.0;
    for (int i = 0; i < on + settle; i++) {
        if (tick(s))
            return -EINTR;
        out.pwm[ch] = i < on ? pwm : 0;
        const int64_t t = mono_ns();
        if (i == 0)
            t_on = t;
        else if (i == on)
            *on_ms = (double)(t - t_on) / 1e6;
        if (t_last && (double)(t - t_last) / 1e6 > *gap_ms)
            *gap_ms = (double)(t - t_last) / 1e6;
        t_last = t;
        int rc = frame_all(s, &out);
        if (rc)
            return rc;
    }
    for (int k = 0; k < XRF_MAX_CHANNELS; k++)
        delta[k] = k < s->nch ? s->pos[k] - start[k] : 0;
    return 0;
}

static int classify(int64_t d, int expect_sign, const struct xrf_sc_channel *c, double stretch)
{
    int64_t noise = c->min_counts / 10 > 3 ? c->min_counts / 10 : 3;
    if (llabs(d) <= noise)
        return P_NONE;
    if ((d > 0 ? 1 : -1) != expect_sign)
        return P_WRONG;
    if (llabs(d) < c->min_counts)
        return P_WEAK;
    if (c->max_counts && (double)llabs(d) > c->max_counts * stretch)
        return P_HIGH;
    return P_OK;
}

static int step_motor(struct sc *s, int ch)
{
    const struct xrf_sc_channel *c = &s->p->ch[ch];
    char id[24], title[160]; /* ids: "motor." + any int; titles: the longest channel name */
    snprintf(id, sizeof id, "motor.%d", ch + 1);
    snprintf(title, sizeof title, "channel %d (%s): motor and encoder", ch + 1, c->name);
    if (!c->motor) {
        skip(s, id, ch + 1, title, "no motor on this channel in the bench profile");
        return 0;
    }
    if (board_missing(s, id, ch, title))
        return 0;
    struct xrf_selfcheck_result r;
    result_init(&r, id, ch + 1, title);
    double duty = c->duty;
    if (duty > s->p->pwm_limit)
        duty = s->p->pwm_limit;
    if (duty > XRF_SC_MAX_DUTY)
        duty = XRF_SC_MAX_DUTY;
    if (duty < 0.0)
        duty = 0.0;
    int16_t pwm = (int16_t)lround(duty * XRF_ICO_PWM_FULL);
    if (pwm > s->pwm_max)
        pwm = s->pwm_max;
    int ms = c->duration_ms > XRF_SC_MAX_PULSE_MS ? XRF_SC_MAX_PULSE_MS : c->duration_ms;
    int64_t dp[XRF_MAX_CHANNELS], dm[XRF_MAX_CHANNELS];
    double on_ms[2] = {ms, ms};
    char what[128];
    /* The longest frame gap the counts survive: half the counter's range at the fastest a
     * plausible pulse moves (max_counts over the pulse), else a fixed bound. A machine that held
     * the check longer gets the pulses again (MOTOR_ATTEMPTS), then an inconclusive warning
     * rather than a diagnosis of cables from counts that cannot be trusted. */
    const double gap_limit_ms = c->max_counts > 0 && ms > 0
                                    ? (double)(XRF_ICO_ENC_MODULO / 2) * ms / (double)c->max_counts
                                    : MOTOR_GAP_MS;
    double gap_ms = 0.0;
    int rc = 0, first = c->first_pulse < 0 ? -1 : 1;
    for (int attempt = 0; attempt < MOTOR_ATTEMPTS; attempt++) {
        s->have_raw = 0;
        clock_start(s);
        rc = frame_all(s, &zero_out);
        /* The profile's first direction first (an axis parked on a stop pulses away from it,
         * then back); dp is the positive pulse's movement and dm the negative one's either way. */
        gap_ms = 0.0;
        for (int k = 0; k < 2 && !rc; k++) {
            int sign = k == 0 ? first : -first;
            double gap = 0.0;
            snprintf(what, sizeof what, "channel %d (%s): PWM %c%.0f %% for %d ms%s", ch + 1,
                     c->name, sign > 0 ? '+' : '-', duty * 100, ms, attempt ? " (again)" : "");
            rc = pulse(s, ch, (int16_t)(sign * pwm), ms, sign > 0 ? dp : dm, &on_ms[k], &gap, what);
            if (gap > gap_ms)
                gap_ms = gap;
        }
        if (rc || gap_ms <= gap_limit_ms)
            break;
    }
    if (rc == -EINTR)
        return rc;
    if (rc) {
        link_broken(s, &r);
        emit(s, &r);
        return -1;
    }
    /* Each way's own measured length, never below the asked one (a pulse is not cut short), and
     * bounded: a pulse stretched past 5x its length is a stalled machine, not a plausible count. */
    double stretch[2];
    for (int k = 0; k < 2; k++) {
        stretch[k] = ms > 0 ? on_ms[k] / ms : 1.0;
        stretch[k] = stretch[k] < 1.0 ? 1.0 : stretch[k] > 5.0 ? 5.0 : stretch[k];
    }
    int sp = classify(dp[ch], c->direction, c, first > 0 ? stretch[0] : stretch[1]);
    int sm = classify(dm[ch], -c->direction, c, first > 0 ? stretch[1] : stretch[0]);
    /* Another encoder that followed both pulses while this one did not: crossed cables. */
    int other = 0;
    for (int k = 0; k < s->nch; k++)
        if (k != ch && llabs(dp[k]) >= c->min_counts && llabs(dm[k]) >= c->min_counts)
            other = k + 1;
    char all_p[XRF_MAX_CHANNELS * 24], all_m[XRF_MAX_CHANNELS * 24];
    json_ints(all_p, sizeof all_p, dp, s->nch);
    json_ints(all_m, sizeof all_m, dm, s->nch);
    SETF(r.data,
         "{\"pwm\":%d,\"duty\":%.3f,\"duration_ms\":%d,\"direction\":%d,\"counts_plus\":%lld,"
         "\"counts_minus\":%lld,\"min_counts\":%d,\"max_counts\":%d,"
         "\"all_plus\":%s,\"all_minus\":%s,\"first_pulse\":%d,\"on_ms_plus\":%.1f,"
         "\"on_ms_minus\":%.1f,\"gap_ms\":%.1f,\"gap_limit_ms\":%.1f}",
         pwm, duty, ms, c->direction, (long long)dp[ch], (long long)dm[ch], c->min_counts,
         c->max_counts, all_p, all_m, first, first > 0 ? on_ms[0] : on_ms[1],
         first > 0 ? on_ms[1] : on_ms[0], gap_ms, gap_limit_ms);
    const char *conn = c->connector;
    if (gap_ms > gap_limit_ms) {
        r.status = XRF_SC_WARN;
        SETF(r.message,
             "inconclusive: this machine held the check for up to %.0f ms between two frames in "
             "each of %d tries, long enough for encoder %d to wrap: its counts (%+lld / %+lld) "
             "say nothing about the wiring",
             gap_ms, MOTOR_ATTEMPTS, ch + 1, (long long)dp[ch], (long long)dm[ch]);
        SETF(r.action, "run the self-check again with less else running on the machine");
        emit(s, &r);
        return 0;
    }
    r.status = XRF_SC_FAIL;
    if (sp == P_OK && sm == P_OK) {
        r.status = XRF_SC_PASS;
        SETF(r.message,
             "a %.0f %% pulse of %d ms moved encoder %d by %+lld counts, the opposite "
             "pulse by %+lld: direction and amount as expected",
             duty * 100, ms, ch + 1, (long long)dp[ch], (long long)dm[ch]);
    } else if (sp == P_NONE && sm == P_NONE && other) {
        SETF(r.message,
             "driving motor %d moved encoder %d, not encoder %d: the encoder cables "
             "of channels %d and %d are swapped",
             ch + 1, other, ch + 1, ch + 1, other);
        SETF(r.action, "plug each encoder cable into the connector of its own motor (%s and %s)",
             conn, s->p->ch[other - 1].connector);
    } else if (sp == P_NONE && sm == P_NONE) {
        SETF(r.message,
             "encoder %d does not count: it stayed at %+lld / %+lld counts while motor "
             "%d was driven %.0f %% each way for %d ms",
             ch + 1, (long long)dp[ch], (long long)dm[ch], ch + 1, duty * 100, ms);
        SETF(r.action,
             "check the encoder cable on %s; if the motor did not turn either, check "
             "the motor cable on %s and the motor power supply",
             conn, conn);
    } else if (sp == P_WRONG && sm == P_WRONG) {
        SETF(r.message,
             "motor %d turns the wrong way: positive PWM moved encoder %d by %+lld "
             "counts (expected %s)",
             ch + 1, ch + 1, (long long)dp[ch], c->direction > 0 ? "up" : "down");
        SETF(r.action,
             "the two motor wires (or the encoder's A/B wires) on %s are swapped: swap "
             "them back; if this bench is wired so on purpose, set direction to %d for channel %d "
             "in the bench profile",
             conn, -c->direction, ch + 1);
    } else if (sp == P_HIGH || sm == P_HIGH) {
        SETF(r.message,
             "encoder %d counted %+lld / %+lld, more than the plausible %d counts for "
             "this pulse (%.0f / %.0f ms on)",
             ch + 1, (long long)dp[ch], (long long)dm[ch], c->max_counts,
             first > 0 ? on_ms[0] : on_ms[1], first > 0 ? on_ms[1] : on_ms[0]);
        SETF(r.action, "check that the right motor/encoder is fitted (counts per revolution, "
                       "gear) or raise max_counts in the bench profile");
    } else if ((sp == P_NONE) != (sm == P_NONE) &&
               (sp == P_OK || sp == P_WEAK || sm == P_OK || sm == P_WEAK)) {
        SETF(r.message,
             "channel %d moves only one way: %+lld counts for the positive pulse, %+lld "
             "for the negative one",
             ch + 1, (long long)dp[ch], (long long)dm[ch]);
        SETF(r.action,
             "if the axis sits at an end stop, move it to the middle and run the check "
             "again; otherwise the motor driver on %s is faulty",
             conn);
    } else if ((sp == P_OK || sp == P_WEAK) && (sm == P_OK || sm == P_WEAK)) {
        SETF(r.message,
             "motor %d moves too little: %+lld / %+lld counts, expected at least %d "
             "each way",
             ch + 1, (long long)dp[ch], (long long)dm[ch], c->min_counts);
        SETF(r.action, "check for stiff or blocked mechanics, a slipping coupling or belt, and "
                       "the motor supply voltage");
    } else {
        SETF(r.message,
             "encoder %d counts inconsistently: %+lld for the positive pulse, %+lld "
             "for the negative one",
             ch + 1, (long long)dp[ch], (long long)dm[ch]);
        SETF(r.action,
             "one of the encoder's A/B wires on %s is loose or the signal is noisy: "
             "check the encoder cable",
             conn);
    }
    emit(s, &r);
    return 0;
}

/* -- digital output loopback -- */
static int wait_pin(struct sc *s, int ch, int dout, int want, int frames, int *seen_after)
{
    /* Written on every path: frame_all's error is any non-zero int, so a caller testing for 1
     * could read it unset (aarch64's gcc says so at -O2, x86's does not). */
    *seen_after = 0;
    struct sc_out out = zero_out;
    out.dout[ch] = (uint8_t)dout;
    for (int i = 0; i < frames; i++) {
        if (tick(s))
            return -EINTR;
        int rc = frame_all(s, &out);
        if (rc)
            return rc;
        if (s->din[2 * ch] == want) {
            *seen_after = i + 1;
            return 1;
        }
    }
    return 0;
}

static int step_dout(struct sc *s, int ch)
{
    const struct xrf_sc_channel *c = &s->p->ch[ch];
    char id[24], title[160]; /* ids: "motor." + any int; titles: the longest channel name */
    snprintf(id, sizeof id, "dout.%d", ch + 1);
    snprintf(title, sizeof title, "channel %d: digital output read back", ch + 1);
    if (!c->loopback) {
        skip(s, id, ch + 1, title,
             "no loopback declared for this output in the bench profile: not "
             "toggled, nothing could read it back");
        return 0;
    }
    if (board_missing(s, id, ch, title))
        return 0;
    struct xrf_selfcheck_result r;
    result_init(&r, id, ch + 1, title);
    progress(s, id, ch + 1, 0.0, "toggling digital output %d, reading input %d pin 1", ch + 1,
             ch + 1);
    s->have_raw = 0;
    clock_start(s);
    int toggles = 3, ok_on = 0, ok_off = 0, lat_on = 0, lat_off = 0, rc = 0;
    /* Start from off, as the reply shows it. */
    int d;
    rc = wait_pin(s, ch, 0, 0, 10, &d);
    int start_low = rc == 1;
    for (int i = 0; i < toggles && rc >= 0; i++) {
        rc = wait_pin(s, ch, 1, 1, 10, &d);
        if (rc == 1) {
            ok_on++;
            lat_on = d;
        }
        if (rc < 0)
            break;
        rc = wait_pin(s, ch, 0, 0, 10, &d);
        if (rc == 1) {
            ok_off++;
            lat_off = d;
        }
    }
    if (rc == -EINTR)
        return rc;
    if (rc < 0) {
        link_broken(s, &r);
        emit(s, &r);
        return -1;
    }
    SETF(r.data,
         "{\"toggles\":%d,\"seen_on\":%d,\"seen_off\":%d,\"frames_on\":%d,\"frames_off\":%d}",
         toggles, ok_on, ok_off, lat_on, lat_off);
    if (start_low && ok_on == toggles && ok_off == toggles) {
        r.status = XRF_SC_PASS;
        SETF(r.message,
             "output %d switched on and off %d times and came back on input %d pin 1 "
             "each time (%d frame(s) later)",
             ch + 1, toggles, ch + 1, lat_on);
    } else if (ok_on == 0 && start_low) {
        r.status = XRF_SC_FAIL;
        SETF(r.message,
             "output %d does not come back on input %d pin 1: the input stayed 0 while "
             "the output was on",
             ch + 1, ch + 1);
        SETF(r.action, "check the loopback wire/plug on %s (output to input pin 1)", c->connector);
    } else if (!start_low || ok_off < toggles) {
        r.status = XRF_SC_FAIL;
        SETF(r.message,
             "input %d pin 1 stays 1 while output %d is off: the input is stuck or "
             "shorted",
             ch + 1, ch + 1);
        SETF(r.action, "check the loopback wire and the input on %s for a short", c->connector);
    } else {
        r.status = XRF_SC_FAIL;
        SETF(r.message, "output %d came back only %d of %d times: a loose loopback connection",
             ch + 1, ok_on, toggles);
        SETF(r.action, "reseat the loopback plug on %s", c->connector);
    }
    emit(s, &r);
    return 0;
}

/* -- digital inputs -- */
static int step_din(struct sc *s, int ch)
{
    const struct xrf_sc_channel *c = &s->p->ch[ch];
    char id[24], title[160]; /* ids: "motor." + any int; titles: the longest channel name */
    snprintf(id, sizeof id, "din.%d", ch + 1);
    snprintf(title, sizeof title, "channel %d: digital inputs", ch + 1);
    if (board_missing(s, id, ch, title))
        return 0;
    struct xrf_selfcheck_result r;
    result_init(&r, id, ch + 1, title);
    progress(s, id, ch + 1, 0.0, "reading input pins of channel %d with the outputs off", ch + 1);
    int ones[2] = {0, 0}, frames = 20;
    s->have_raw = 0;
    clock_start(s);
    /* Outputs off for a few frames first: a loopback shows the previous frame's output. */
    for (int i = 0; i < 2 + frames; i++) {
        if (tick(s))
            return -EINTR;
        if (frame_all(s, &zero_out)) {
            link_broken(s, &r);
            emit(s, &r);
            return -1;
        }
        if (i >= 2)
            for (int k = 0; k < 2; k++)
                ones[k] += s->din[2 * ch + k];
    }
    int level[2];
    const char *desc[2];
    for (int k = 0; k < 2; k++) {
        level[k] = ones[k] == 0 ? 0 : ones[k] == frames ? 1 : -1;
        desc[k] = level[k] == 0 ? "0" : level[k] == 1 ? "1" : "flickering";
    }
    SETF(r.data,
         "{\"pin1\":%d,\"pin2\":%d,\"pin1_ones\":%d,\"pin2_ones\":%d,\"frames\":%d,"
         "\"idle\":[%d,%d]}",
         level[0] < 0 ? 2 : level[0], level[1] < 0 ? 2 : level[1], ones[0], ones[1], frames,
         c->din_idle[0], c->din_idle[1]);
    int bad = 0;
    for (int k = 0; k < 2 && !bad; k++) {
        if (c->din_idle[k] < 0 || level[k] == c->din_idle[k])
            continue;
        bad = k + 1;
    }
    if (!bad) {
        r.status = XRF_SC_PASS;
        SETF(r.message, "pin 1 (%s) reads %s, pin 2 (%s) reads %s%s", c->pin_name[0], desc[0],
             c->pin_name[1], desc[1],
             c->din_idle[0] < 0 && c->din_idle[1] < 0 ? " (reported only: the profile expects "
                                                        "no level)"
                                                      : ", as expected");
    } else {
        int k = bad - 1;
        r.status = XRF_SC_FAIL;
        if (level[k] < 0)
            SETF(r.message,
                 "input pin %d of channel %d (%s) flickers (1 in %d of %d frames) with "
                 "nothing connected to drive it",
                 bad, ch + 1, c->pin_name[k], ones[k], frames);
        else
            SETF(r.message,
                 "input pin %d of channel %d (%s) reads %d with the outputs off "
                 "(expected %d): the input is stuck or its wire is shorted",
                 bad, ch + 1, c->pin_name[k], level[k], c->din_idle[k]);
        SETF(r.action,
             "check the wiring on %s (a pressed switch also reads 1); if nothing is "
             "connected there, the input on the ico board is damaged",
             c->connector);
    }
    emit(s, &r);
    return 0;
}

/* -- link timing -- */
static int cmp_double(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return x < y ? -1 : x > y;
}

static int step_timing(struct sc *s)
{
    struct xrf_selfcheck_result r;
    result_init(&r, "timing", 0, "SPI link timing");
    int n = s->p->timing_frames;
    double *us = malloc(sizeof *us * (size_t)n);
    if (!us) {
        r.status = XRF_SC_FAIL;
        SETF(r.message, "out of memory");
        emit(s, &r);
        return -1;
    }
    uint8_t tx[XRF_ICO_FRAME], rx[XRF_ICO_FRAME];
    static const struct xrf_ico_out zero;
    xrf_ico_encode_all(&zero, 0, tx);
    double sum = 0;
    for (int i = 0; i < n; i++) {
        if (aborted(s)) {
            free(us);
            return -EINTR;
        }
        if (i % 100 == 0)
            progress(s, "timing", 0, (double)i / n, "timing frame %d of %d", i, n);
        struct timespec a, b;
        clock_gettime(CLOCK_MONOTONIC, &a);
        int rc = xfer(s, tx, rx);
        clock_gettime(CLOCK_MONOTONIC, &b);
        if (rc) {
            free(us);
            link_broken(s, &r);
            emit(s, &r);
            return -1;
        }
        us[i] = (double)(b.tv_sec - a.tv_sec) * 1e6 + (double)(b.tv_nsec - a.tv_nsec) / 1e3;
        sum += us[i];
    }
    qsort(us, (size_t)n, sizeof *us, cmp_double);
    double mn = us[0], mx = us[n - 1], med = us[n / 2], mean = sum / n;
    double p99 = us[(int)((n - 1) * 0.99)];
    free(us);
    SETF(r.data,
         "{\"frames\":%d,\"min_us\":%.2f,\"median_us\":%.2f,\"mean_us\":%.2f,"
         "\"p99_us\":%.2f,\"max_us\":%.2f,\"warn_median_us\":%.1f,\"fail_median_us\":%.1f,"
         "\"warn_max_us\":%.1f}",
         n, mn, med, mean, p99, mx, s->p->warn_median_us, s->p->fail_median_us, s->p->warn_max_us);
    if (med > s->p->fail_median_us) {
        r.status = XRF_SC_FAIL;
        SETF(r.message,
             "the link is slow: one frame takes %.1f us (median; min %.1f, max %.1f), "
             "above the %.0f us this bench allows; a 1 kHz loop spends that much of every "
             "1000 us cycle waiting for the board",
             med, mn, mx, s->p->fail_median_us);
        SETF(r.action, "check the SPI clock setting and CPU load (stop other programs); the EVL "
                       "out-of-band transport (evl-spidev) is faster than in-band spidev");
    } else if (med > s->p->warn_median_us || mx > s->p->warn_max_us) {
        r.status = XRF_SC_WARN;
        SETF(r.message,
             "the link is slower than expected: median %.1f us, max %.1f us (warn "
             "above %.0f us median or %.0f us max)",
             med, mx, s->p->warn_median_us, s->p->warn_max_us);
        SETF(r.action,
             "usable, but look at the CPU load and the SPI clock if loops miss deadlines");
    } else {
        r.status = XRF_SC_PASS;
        SETF(r.message, "one frame takes %.1f us (median; min %.1f, max %.1f over %d frames)", med,
             mn, mx, n);
    }
    emit(s, &r);
    return 0;
}

int xrf_selfcheck_run(struct xrf_ico_transport *t, const struct xrf_selfcheck_profile *p,
                      const struct xrf_selfcheck_hooks *hooks, struct xrf_selfcheck_summary *sum)
{
    if (!t || !p || !sum)
        return -EINVAL;
    memset(sum, 0, sizeof *sum);
    /* The profile was validated in Python; the hard limits hold here whatever the input says
     * (one definition: xrf/selfcheck_limits.h). */
    struct xrf_selfcheck_profile prof = *p;
    if (prof.period_us < XRF_SC_MIN_PERIOD_US)
        prof.period_us = XRF_SC_MIN_PERIOD_US;
    if (prof.period_us > XRF_SC_MAX_PERIOD_US)
        prof.period_us = XRF_SC_MAX_PERIOD_US;
    if (prof.settle_ms < 0)
        prof.settle_ms = 0;
    if (prof.settle_ms > XRF_SC_MAX_SETTLE_MS)
        prof.settle_ms = XRF_SC_MAX_SETTLE_MS;
    if (prof.echo_frames < 1)
        prof.echo_frames = 1;
    if (prof.echo_frames > XRF_SC_MAX_FRAMES)
        prof.echo_frames = XRF_SC_MAX_FRAMES;
    if (prof.timing_frames < 1)
        prof.timing_frames = 1;
    if (prof.timing_frames > XRF_SC_MAX_FRAMES)
        prof.timing_frames = XRF_SC_MAX_FRAMES;
    double limit = prof.pwm_limit > XRF_SC_MAX_DUTY ? XRF_SC_MAX_DUTY : prof.pwm_limit;
    if (limit < 0.0)
        limit = 0.0;
    struct sc s = {.t = t, .p = &prof, .h = hooks, .sum = sum};
    /* The bench: the boards the transport has, and of their channels the bench's count. */
    int boards = t->xfer_board && t->boards > 1 ? t->boards : 1;
    if (boards > XRF_MAX_BOARDS)
        boards = XRF_MAX_BOARDS;
    s.nch = prof.channels > 0 && prof.channels < boards * XRF_ICO_CHANNELS
                ? prof.channels
                : boards * XRF_ICO_CHANNELS;
    s.boards = (s.nch + XRF_ICO_CHANNELS - 1) / XRF_ICO_CHANNELS;
    s.board_ok[0] = 1;
    /* The frame builder clamps to this whatever a step asks for: never beyond 20 %. */
    s.pwm_max = xrf_ico_pwm_max(limit);

    int rc = step_init(&s);
    if (rc == 0)
        xrf_selfcheck_zero_outputs(t);
    if (rc == 0 && !aborted(&s))
        rc = step_boards(&s);
    if (rc == 0 && !aborted(&s))
        rc = step_echo(&s);
    if (rc == 0 && !aborted(&s))
        rc = step_reset(&s);
    for (int ch = 0; ch < s.nch && rc == 0 && !aborted(&s); ch++)
        rc = step_motor(&s, ch);
    for (int ch = 0; ch < s.nch && rc == 0 && !aborted(&s); ch++)
        rc = step_dout(&s, ch);
    for (int ch = 0; ch < s.nch && rc == 0 && !aborted(&s); ch++)
        rc = step_din(&s, ch);
    if (rc == 0 && !aborted(&s))
        rc = step_timing(&s);

    if (aborted(&s) || rc == -EINTR) {
        sum->aborted = 1;
    } else if (rc < 0) {
        /* Board absent or link broken: every step not yet reported is skipped with the reason. */
        const char *why = s.xfer_err ? "not run: an SPI transfer failed earlier"
                                     : "not run: the ico board did not answer INIT";
        int total = planned_id(&s, -1, NULL, 0);
        for (int i = 0; i < total && i < (int)sizeof s.done; i++) {
            if (s.done[i])
                continue;
            char id[24], title[96];
            planned_id(&s, i, id, sizeof id);
            planned_title(&s, id, title, sizeof title);
            skip(&s, id, id_channel(id), title, why);
        }
    }
    sum->outputs_zeroed = xrf_selfcheck_zero_outputs(t) == 0;
    if (sum->aborted)
        return -EINTR;
    return sum->failed ? 1 : 0;
}
