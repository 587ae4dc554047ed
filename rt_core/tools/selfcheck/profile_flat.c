/*
 * profile_flat.c — the bench profile as the checker receives it: flat key=value lines, already
 * validated by appliance/xrflab/profiles.py (the only validator, with per-field errors). Here
 * only the form is checked: a known key, a well-formed value. Ranges are not (they would be a
 * copy of the schema); xrf_selfcheck_run clamps to the hard limits of xrf/selfcheck_limits.h.
 *
 *   name=relbot
 *   limits.pwm_limit=0.2
 *   channel.1.duty=0.15
 *   channel.1.pin.2.idle=0          (-1: not checked)
 *
 * Text values escape a backslash as "\\" and a control character as "\xHH", so one value is
 * one line. Empty lines and lines starting with '#' are ignored.
 */
#define _POSIX_C_SOURCE 200809L

#include <errno.h>
#include <limits.h>
#include <math.h>
#include <stddef.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "selfcheck.h"

enum kind { K_TEXT, K_INT, K_REAL };

struct key {
    const char *name;
    enum kind kind;
    size_t offset; /* in the struct the key belongs to */
    size_t size;   /* of a text field */
};

#define P_FIELD(n, k, f)                                   \
    {                                                      \
        n, k, offsetof(struct xrf_selfcheck_profile, f),   \
            sizeof(((struct xrf_selfcheck_profile *)0)->f) \
    }
#define C_FIELD(n, k, f)                                                                  \
    {                                                                                     \
        n, k, offsetof(struct xrf_sc_channel, f), sizeof(((struct xrf_sc_channel *)0)->f) \
    }

/* The names are the JSON paths of the profile schema (appliance/xrflab/profiles.py); the writer,
 * appliance/xrflab/profile_flat.py, lists the same keys. */
static const struct key profile_keys[] = {
    P_FIELD("name", K_TEXT, name),
    P_FIELD("limits.pwm_limit", K_REAL, pwm_limit),
    P_FIELD("pulse.period_us", K_INT, period_us),
    P_FIELD("pulse.settle_ms", K_INT, settle_ms),
    P_FIELD("pulse.reset_tolerance_counts", K_INT, reset_tolerance),
    P_FIELD("link.echo_frames", K_INT, echo_frames),
    P_FIELD("link.timing_frames", K_INT, timing_frames),
    P_FIELD("link.warn_median_us", K_REAL, warn_median_us),
    P_FIELD("link.fail_median_us", K_REAL, fail_median_us),
    P_FIELD("link.warn_max_us", K_REAL, warn_max_us),
};

static const struct key channel_keys[] = {
    C_FIELD("name", K_TEXT, name),
    C_FIELD("connector", K_TEXT, connector),
    C_FIELD("motor", K_INT, motor),
    C_FIELD("direction", K_INT, direction),
    C_FIELD("first_pulse", K_INT, first_pulse),
    C_FIELD("duty", K_REAL, duty),
    C_FIELD("duration_ms", K_INT, duration_ms),
    C_FIELD("min_counts", K_INT, min_counts),
    C_FIELD("max_counts", K_INT, max_counts),
    C_FIELD("loopback", K_INT, loopback),
};

static int unescape(const char *src, char *dst, size_t size)
{
    size_t o = 0;
    for (const char *p = src; *p; p++) {
        char c = *p;
        if (c == '\\') {
            if (p[1] == '\\') {
                p++;
            } else if (p[1] == 'x' && p[2] && p[3]) {
                char hex[3] = {p[2], p[3], 0}, *end;
                long v = strtol(hex, &end, 16);
                if (*end)
                    return -EINVAL;
                c = (char)v;
                p += 3;
            } else {
                return -EINVAL;
            }
        }
        if (o + 1 < size) /* longer text is cut, as the fixed fields always did */
            dst[o++] = c;
    }
    dst[o] = 0;
    return 0;
}

static int store(const struct key *k, void *base, const char *value)
{
    char *field = (char *)base + k->offset;
    char *end;
    errno = 0;
    switch (k->kind) {
    case K_TEXT:
        return unescape(value, field, k->size);
    case K_INT: {
        long v = strtol(value, &end, 10);
        if (!*value || *end || errno || v < INT_MIN || v > INT_MAX)
            return -EINVAL;
        *(int *)field = (int)v;
        return 0;
    }
    case K_REAL: {
        double v = strtod(value, &end);
        if (!*value || *end || errno || !isfinite(v))
            return -EINVAL;
        *(double *)field = v;
        return 0;
    }
    }
    return -EINVAL;
}

static const struct key *find(const struct key *keys, size_t n, const char *name)
{
    for (size_t i = 0; i < n; i++)
        if (strcmp(keys[i].name, name) == 0)
            return &keys[i];
    return NULL;
}

/* "channel.N.rest": the channel index N - 1 and rest; -ENOENT when the key is no channel key,
 * -ERANGE when N is not 1..XRF_MAX_CHANNELS (digits only, no sign, no leading zero: the writer
 * writes plain numbers, and anything else must not alias another channel). */
static int channel_of(const char *key, const char **rest)
{
    if (strncmp(key, "channel.", 8) != 0)
        return -ENOENT;
    const char *d = key + 8;
    int n = 0, len = 0;
    while (d[len] >= '0' && d[len] <= '9') {
        if (len < 6)
            n = n * 10 + (d[len] - '0');
        len++;
    }
    if (len == 0 || d[len] != '.')
        return -ENOENT;
    if (len > 2 || d[0] == '0' || n < 1 || n > XRF_MAX_CHANNELS)
        return -ERANGE;
    *rest = d + len + 1;
    return n - 1;
}

static int apply(struct xrf_selfcheck_profile *p, const char *key, const char *value)
{
    const struct key *k = find(profile_keys, sizeof profile_keys / sizeof *profile_keys, key);
    if (k)
        return store(k, p, value);
    const char *rest;
    int ch = channel_of(key, &rest);
    if (ch < 0)
        return ch;
    struct xrf_sc_channel *c = &p->ch[ch];
    c->listed = 1;
    k = find(channel_keys, sizeof channel_keys / sizeof *channel_keys, rest);
    if (k)
        return store(k, c, value);
    /* pin.P.name / pin.P.idle, P in 1..2 */
    if (strncmp(rest, "pin.", 4) != 0 || (rest[4] != '1' && rest[4] != '2') || rest[5] != '.')
        return -ENOENT;
    int pin = rest[4] - '1';
    if (strcmp(rest + 6, "name") == 0)
        return unescape(value, c->pin_name[pin], sizeof c->pin_name[pin]);
    if (strcmp(rest + 6, "idle") == 0) {
        struct key idle = {"idle", K_INT, 0, 0};
        return store(&idle, &c->din_idle[pin], value);
    }
    return -ENOENT;
}

int xrf_selfcheck_profile_read(FILE *in, struct xrf_selfcheck_profile *p, char *err, size_t errlen)
{
    if (err && errlen)
        err[0] = 0;
    if (!in || !p)
        return -EINVAL;
    char *line = NULL;
    size_t cap = 0;
    ssize_t len;
    int lineno = 0, rc = 0;
    while (rc == 0 && (len = getline(&line, &cap, in)) >= 0) {
        lineno++;
        while (len > 0 && (line[len - 1] == '\n' || line[len - 1] == '\r'))
            line[--len] = 0;
        if (len == 0 || line[0] == '#')
            continue;
        char *eq = strchr(line, '=');
        if (!eq) {
            if (err && errlen)
                snprintf(err, errlen,
                         "profile line %d is not key=value (the checker reads the flat form "
                         "xrflab.profiles writes, not JSON: run it through `xrf selfcheck`)",
                         lineno);
            rc = -EINVAL;
            break;
        }
        *eq = 0;
        int r = apply(p, line, eq + 1);
        if (r == -ERANGE && err && errlen)
            snprintf(err, errlen,
                     "profile line %d: '%.64s' names a channel no bench has (channels are 1 "
                     "to %d: %d ico boards of %d)",
                     lineno, line, XRF_MAX_CHANNELS, XRF_MAX_BOARDS, XRF_ICO_CHANNELS);
        else if (r && err && errlen)
            snprintf(err, errlen, "profile line %d: %s '%.64s'", lineno,
                     r == -ENOENT ? "unknown key" : "malformed value for", line);
        rc = r ? -EINVAL : 0;
    }
    free(line);
    return rc;
}

int xrf_selfcheck_profile_fits(const struct xrf_selfcheck_profile *p, int channels, char *err,
                               size_t errlen)
{
    for (int i = 0; i < XRF_MAX_CHANNELS; i++) {
        if (!p->ch[i].listed || i < channels)
            continue;
        if (err && errlen)
            snprintf(err, errlen,
                     "the profile lists channel %d (%s), but this bench has %d channel%s (%d ico "
                     "board%s of %d): remove the channel from the profile or check it on the "
                     "bench it belongs to",
                     i + 1, p->ch[i].name, channels, channels == 1 ? "" : "s",
                     (channels + XRF_ICO_CHANNELS - 1) / XRF_ICO_CHANNELS,
                     channels > XRF_ICO_CHANNELS ? "s" : "", XRF_ICO_CHANNELS);
        return -ERANGE;
    }
    return 0;
}

void xrf_selfcheck_profile_dump(FILE *out, const struct xrf_selfcheck_profile *p)
{
    char buf[256];
    fprintf(out, "{\"event\":\"profile\",\"name\":%s,\"pwm_limit\":%.17g,\"period_us\":%d,",
            xrf_selfcheck_json_string(p->name, buf, sizeof buf), p->pwm_limit, p->period_us);
    fprintf(
        out,
        "\"settle_ms\":%d,\"reset_tolerance\":%d,\"echo_frames\":%d,\"timing_frames\":%d,"
        "\"warn_median_us\":%.17g,\"fail_median_us\":%.17g,\"warn_max_us\":%.17g,\"channels\":[",
        p->settle_ms, p->reset_tolerance, p->echo_frames, p->timing_frames, p->warn_median_us,
        p->fail_median_us, p->warn_max_us);
    /* The first four always (the one-board form the tests know), further ones when listed. */
    for (int i = 0; i < XRF_MAX_CHANNELS; i++) {
        const struct xrf_sc_channel *c = &p->ch[i];
        if (i >= XRF_ICO_CHANNELS && !c->listed)
            continue;
        char conn[128], pin0[128], pin1[128];
        fprintf(out,
                "%s{\"channel\":%d,\"name\":%s,\"connector\":%s,\"motor\":%d,\"direction\":%d,"
                "\"first_pulse\":%d,\"duty\":%.17g,"
                "\"duration_ms\":%d,\"min_counts\":%d,\"max_counts\":%d,\"loopback\":%d,"
                "\"din_idle\":[%d,%d],\"pin_name\":[%s,%s]}",
                i ? "," : "", i + 1, xrf_selfcheck_json_string(c->name, buf, sizeof buf),
                xrf_selfcheck_json_string(c->connector, conn, sizeof conn), c->motor, c->direction,
                c->first_pulse, c->duty, c->duration_ms, c->min_counts, c->max_counts, c->loopback,
                c->din_idle[0], c->din_idle[1],
                xrf_selfcheck_json_string(c->pin_name[0], pin0, sizeof pin0),
                xrf_selfcheck_json_string(c->pin_name[1], pin1, sizeof pin1));
    }
    fprintf(out, "]}\n");
    fflush(out);
}
