/*
 * selfcheck.h — private to the xrf-selfcheck tool (not part of the runtime library a controller
 * links): the bench self-check: is the ico board there, is the SPI link intact, do the
 * motors, encoders and digital I/O of this bench work as its bench profile says?
 *
 * The steps talk to the board through the same xrf_ico_transport and frame builders (ico.c) as
 * the loop. Every step ends as pass / warn / fail / skip with a plain-language explanation and
 * what to do. Whatever happens (end, failure, abort), the outputs are zeroed at the end:
 * RESET, then ALL with zero PWM and all digital outputs off. See docs/educators/selfcheck.md.
 *
 * Hard limits, whatever the profile says (xrf/selfcheck_limits.h): |duty| <= XRF_SC_MAX_DUTY,
 * pulse <= XRF_SC_MAX_PULSE_MS, ... The profile reaches the tool already validated, as flat
 * key=value lines (profile_flat.c); the schema and its checks live in appliance/xrflab/profiles.py.
 */
#ifndef XRF_SELFCHECK_TOOL_H
#define XRF_SELFCHECK_TOOL_H

#include <signal.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>

#include "xrf/channels.h"
#include "xrf/ico.h"
#include "xrf/selfcheck_limits.h"

#ifdef __cplusplus
extern "C" {
#endif

#define XRF_SC_PASS 0
#define XRF_SC_WARN 1
#define XRF_SC_FAIL 2
#define XRF_SC_SKIP 3

#define XRF_SC_TEXT 384
#define XRF_SC_DATA 768

struct xrf_sc_channel {
    char name[64];      /* "left wheel" */
    char connector[32]; /* "PMOD 1": where the educator finds the cable */
    int motor;          /* 1: a motor + encoder is wired to this channel */
    int direction;      /* +1: positive PWM counts the encoder up; -1: down */
    int first_pulse;    /* sign of the first pulse's PWM (+1 default, -1: negative first): an
                         * axis parked on a stop pulses away from it first (docs/educators/
                         * selfcheck.md), then back */
    double duty;        /* pulse duty as a fraction of full scale (<= XRF_SC_MAX_DUTY) */
    int duration_ms;    /* pulse length each way (<= XRF_SC_MAX_PULSE_MS) */
    int min_counts;     /* |counts| a pulse must at least move the encoder */
    int max_counts;     /* 0 = no upper bound; more than this is implausible */
    int loopback;       /* 1: digital output wired back to input pin 1 of this channel */
    int din_idle[2];    /* expected level of pin 1/2 with outputs off; -1 = not checked */
    char pin_name[2][64];
    int listed; /* 1: the profile has a key of this channel (xrf_selfcheck_profile_fits) */
};

struct xrf_selfcheck_profile {
    char name[64];
    double pwm_limit;      /* fraction of full scale handed to the frame builder (<= 0.2) */
    int period_us;         /* frame period of the timed loops (default 1000) */
    int settle_ms;         /* zero-PWM time after each pulse, encoders still read */
    int reset_tolerance;   /* counts an encoder may read after RESET */
    int echo_frames;       /* TEST frames (default 1000) */
    int timing_frames;     /* ALL frames timed (default 1000) */
    double warn_median_us; /* link timing: warn above this median */
    double fail_median_us; /* link timing: fail above this median */
    double warn_max_us;    /* link timing: warn above this maximum */
    /* The bench's channel count, 1..XRF_MAX_CHANNELS: channels 1..channels on ceil(channels / 4)
     * ico boards are checked. 0: every channel of the boards the transport has. Set by the
     * tool from the bench (the simulated plant's row), not from the profile. */
    int channels;
    struct xrf_sc_channel ch[XRF_MAX_CHANNELS];
};

/* One finished step. id: "spi", "init", "board.B" (ico board B = 2, 3 of a bench of several
 * boards), "echo", "reset", "motor.N", "dout.N", "din.N", "timing". channel: 1..the bench's
 * count for per-channel steps, 0 otherwise. data: a JSON object text with the
 * measured values ("{}" when none). */
struct xrf_selfcheck_result {
    char id[16];
    int channel;
    int status;
    char title[96];
    char message[XRF_SC_TEXT]; /* what was found, in plain language */
    char action[XRF_SC_TEXT];  /* what to do ("" when nothing) */
    char data[XRF_SC_DATA];
};

struct xrf_selfcheck_hooks {
    /* A step starts or makes progress (fraction 0..1 of that step). May be NULL. */
    void (*progress)(void *user, const char *id, int channel, const char *text, double fraction);
    /* A step finished. May be NULL. */
    void (*result)(void *user, const struct xrf_selfcheck_result *r);
    void *user;
    /* Checked between frames: non-zero = abort (set from a signal handler). May be NULL. */
    volatile sig_atomic_t *abort_flag;
};

struct xrf_selfcheck_summary {
    int passed, warned, failed, skipped;
    int aborted;        /* 1 if abort_flag stopped the check */
    int outputs_zeroed; /* 1 if the final RESET + zero ALL went through */
};

/* Where the board is. transport: "sim", "spidev", "evl-spidev". */
struct xrf_selfcheck_target {
    const char *transport;
    const char *device;                  /* spidev path (default /dev/spidev0.0) */
    uint32_t speed_hz;                   /* default 31 MHz */
    const char *sim;                     /* "relbot" / "jiwy" */
    const char *faults;                  /* xrf_sim_parse_faults spec, may be NULL */
    struct xrf_sim_outputs *sim_outputs; /* mirror of the simulated board, may be NULL */
};

/* Defaults: no motors, no loopbacks, pins unchecked, 1 ms period, limits as documented. */
void xrf_selfcheck_profile_defaults(struct xrf_selfcheck_profile *p);
/* Reads a validated bench profile in its flat form (one key=value per line, as
 * xrflab.profile_flat writes it: "channel.1.duty=0.15") on top of what *p holds. Only the
 * form is checked here, no ranges (xrf_selfcheck_run clamps to the hard limits). Returns 0, or
 * -EINVAL for an unknown key or a malformed line/value, with the line number and key in err. */
int xrf_selfcheck_profile_read(FILE *in, struct xrf_selfcheck_profile *p, char *err, size_t errlen);
/* 0 when every channel the profile lists (channel.N keys) is one of the bench's `channels`;
 * else -ERANGE with a plain-language sentence in err naming the channel and the bench. */
int xrf_selfcheck_profile_fits(const struct xrf_selfcheck_profile *p, int channels, char *err,
                               size_t errlen);
/* Writes *p as one JSON object line {"event":"profile",...} (xrf-selfcheck --dump-profile):
 * what the checker will use, for tests that the flat form reaches every field. */
void xrf_selfcheck_profile_dump(FILE *out, const struct xrf_selfcheck_profile *p);

/* The "spi" step: opens the transport and says what went wrong in plain language. Returns 0
 * (r->status PASS, *out set) or -errno (r->status FAIL, *out NULL). -EINVAL: bad target. */
int xrf_selfcheck_open(const struct xrf_selfcheck_target *target, struct xrf_ico_transport **out,
                       struct xrf_selfcheck_result *r);

/* Runs every step after "spi" on an open transport, reporting through hooks, then zeroes the
 * outputs. Returns 0 when no step failed, 1 when some failed, -EINTR when aborted, -EINVAL on a
 * bad argument. */
int xrf_selfcheck_run(struct xrf_ico_transport *t, const struct xrf_selfcheck_profile *p,
                      const struct xrf_selfcheck_hooks *hooks, struct xrf_selfcheck_summary *sum);

/* RESET, then ALL with zero PWM and outputs off. Returns 0 or the first -errno. */
int xrf_selfcheck_zero_outputs(struct xrf_ico_transport *t);

const char *xrf_selfcheck_status_name(int status); /* "pass", "warn", "fail", "skip" */

/* Writes s as a JSON string literal (with quotes) into buf; returns buf. */
char *xrf_selfcheck_json_string(const char *s, char *buf, size_t len);

#ifdef __cplusplus
}
#endif

#endif /* XRF_SELFCHECK_TOOL_H */
