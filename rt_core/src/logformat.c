/* The xrflog segment header (xrf/logformat.h): the one place that composes it. */
#include "xrf/logformat.h"

#include <errno.h>
#include <stdarg.h>
#include <stdio.h>
#include <string.h>

#include "xrf/channels.h"

#if __BYTE_ORDER__ != __ORDER_LITTLE_ENDIAN__
#error "the xrflog prefix and records are little-endian: this writer would need byte swaps"
#endif

const char xrf_logfile_magic[XRF_LOGFILE_MAGIC_SIZE] = {'X', 'R', 'F', 'L', 'O', 'G', '1', '\n'};

const struct xrf_logfile_type xrf_logfile_types[XRF_LOG_NTYPES] = {
    {XRF_LOG_BOOL, 1, "bool", "bool", "|b1"},
    {XRF_LOG_CHAR, 1, "char", "char", "|S1"},
    {XRF_LOG_INT, 4, "int", "int32", "<i4"},
    {XRF_LOG_FLOAT, 4, "float", "float32", "<f4"},
    {XRF_LOG_DOUBLE, 8, "double", "float64", "<f8"},
    {XRF_LOG_LONG_INT, 8, "long int", "int64", "<i8"},
};

const struct xrf_logfile_type *xrf_logfile_type_of(int32_t code)
{
    if (code < 1 || code > XRF_LOG_NTYPES)
        return NULL;
    /* The table is in code order (logformat.h); a wrong row would show up in every test. */
    return &xrf_logfile_types[code - 1];
}

/* The JSON text around the values; kept as macros so that the bound below is their real size. */
#define HEAD_FORMAT "{\"format\":\"xrflog\",\"version\":"
#define HEAD_PROGRAM ",\"program\":"
#define HEAD_PROJECT ",\"project\":"
#define HEAD_BUILD ",\"build\":"
#define HEAD_RUN ",\"run\":"
#define HEAD_NUMBERS                                                                        \
    ",\"pid\":%d,\"cycle_freq\":%u,\"start_unix_ns\":%lld,\"start_mono_ns\":%lld,"          \
    "\"record_header\":[[\"seq\",\"uint64\"],[\"cycle\",\"uint64\"],[\"t_ns\",\"int64\"]]," \
    "\"record_size\":%u,\"variables\":["
#define VAR_NAME ",{\"name\":"
#define VAR_REST ",\"type\":%d,\"dtype\":\"%s\",\"offset\":%d}"
#define TAIL "]}\n"

#define ESCAPED_MAX(n) (2 + 6 * (size_t)(n)) /* quotes + every byte as \u00XX */
#define INT_TEXT_MAX 20                      /* "-9223372036854775808" */
#define DTYPE_MAX 7                          /* "float32", or "?" */
_Static_assert(XRF_LOGFILE_PREFIX_SIZE + sizeof HEAD_FORMAT + INT_TEXT_MAX + sizeof HEAD_PROGRAM +
                       sizeof HEAD_PROJECT + sizeof HEAD_BUILD + sizeof HEAD_RUN +
                       4 * ESCAPED_MAX(XRF_LOGFILE_TEXT_MAX) + sizeof HEAD_NUMBERS +
                       5 * INT_TEXT_MAX +
                       XRF_LOG_VARS_MAX * (sizeof VAR_NAME + ESCAPED_MAX(XRF_NAME_MAX) +
                                           sizeof VAR_REST + 3 * INT_TEXT_MAX + DTYPE_MAX) +
                       sizeof TAIL + XRF_LOGFILE_ALIGN - 1 <=
                   XRF_LOGFILE_HEADER_MAX,
               "XRF_LOGFILE_HEADER_MAX does not bound every header");

struct out {
    char *p;
    size_t left;
    int full; /* something did not fit: the result is -ENOSPC */
};

static void put(struct out *o, const char *s, size_t n)
{
    if (o->full || n > o->left) {
        o->full = 1;
        return;
    }
    memcpy(o->p, s, n);
    o->p += n;
    o->left -= n;
}

static void putf(struct out *o, const char *fmt, ...) __attribute__((format(printf, 2, 3)));
static void putf(struct out *o, const char *fmt, ...)
{
    if (o->full)
        return;
    va_list ap;
    va_start(ap, fmt);
    int n = vsnprintf(o->p, o->left, fmt, ap);
    va_end(ap);
    if (n < 0 || (size_t)n >= o->left) { /* >=: vsnprintf needs room for its NUL */
        o->full = 1;
        return;
    }
    o->p += n;
    o->left -= (size_t)n;
}

/* Length of the well-formed UTF-8 sequence at s[0..n) (RFC 3629: no overlongs, surrogates or
 * code points above U+10FFFF), 0 when s[0] starts none. */
static size_t utf8_len(const unsigned char *s, size_t n)
{
    unsigned char c = s[0];
    size_t len;
    unsigned char lo = 0x80, hi = 0xBF; /* allowed range of the second byte */
    if (c < 0x80)
        return 1;
    if (c >= 0xC2 && c <= 0xDF)
        len = 2;
    else if (c >= 0xE0 && c <= 0xEF) {
        len = 3;
        if (c == 0xE0)
            lo = 0xA0;
        else if (c == 0xED)
            hi = 0x9F;
    } else if (c >= 0xF0 && c <= 0xF4) {
        len = 4;
        if (c == 0xF0)
            lo = 0x90;
        else if (c == 0xF4)
            hi = 0x8F;
    } else
        return 0;
    if (len > n || s[1] < lo || s[1] > hi)
        return 0;
    for (size_t i = 2; i < len; i++)
        if (s[i] < 0x80 || s[i] > 0xBF)
            return 0;
    return len;
}

/* A JSON string of s[0..n): '"' and '\\' backslashed, control characters as \u00XX (the form
 * the first writer used, kept so that headers stay byte-identical), bytes that are not UTF-8
 * as U+FFFD (a JSON text must be UTF-8, or the reader would take the header for damage). */
static void put_string(struct out *o, const char *s, size_t n)
{
    const unsigned char *u = (const unsigned char *)s;
    put(o, "\"", 1);
    for (size_t i = 0; i < n;) {
        unsigned char c = u[i];
        if (c == '"' || c == '\\') {
            char esc[2] = {'\\', (char)c};
            put(o, esc, 2);
            i++;
        } else if (c < 0x20) {
            putf(o, "\\u%04x", c);
            i++;
        } else {
            size_t len = utf8_len(u + i, n - i);
            if (len == 0) {
                put(o, "\xEF\xBF\xBD", 3);
                i++;
            } else {
                put(o, s + i, len);
                i += len;
            }
        }
    }
    put(o, "\"", 1);
}

/* A text of the ident: "" for NULL; -ENAMETOOLONG past XRF_LOGFILE_TEXT_MAX. */
static int put_text(struct out *o, const char *key, const char *s)
{
    size_t n = s ? strnlen(s, XRF_LOGFILE_TEXT_MAX + 1) : 0;
    if (n > XRF_LOGFILE_TEXT_MAX)
        return -ENAMETOOLONG;
    put(o, key, strlen(key));
    put_string(o, s ? s : "", n);
    return 0;
}

int xrf_logfile_header(char *buf, size_t cap, const struct xrf_logfile_ident *id,
                       const struct xrf_log_meta *meta, uint32_t stride)
{
    if (buf == NULL || id == NULL || meta == NULL)
        return -EINVAL;
    if (cap < XRF_LOGFILE_PREFIX_SIZE)
        return -ENOSPC;
    struct out o = {buf + XRF_LOGFILE_PREFIX_SIZE, cap - XRF_LOGFILE_PREFIX_SIZE, 0};
    putf(&o, HEAD_FORMAT "%d", XRF_LOGFILE_VERSION);
    int err = put_text(&o, HEAD_PROGRAM, id->program);
    if (err == 0)
        err = put_text(&o, HEAD_PROJECT, id->project);
    if (err == 0)
        err = put_text(&o, HEAD_BUILD, id->build);
    if (err == 0)
        err = put_text(&o, HEAD_RUN, id->run);
    if (err)
        return err;
    putf(&o, HEAD_NUMBERS, (int)id->pid, (unsigned)id->cycle_freq, (long long)id->start_unix_ns,
         (long long)id->start_mono_ns, (unsigned)meta->record_size);
    uint32_t nvars = meta->nvars < XRF_LOG_VARS_MAX ? meta->nvars : XRF_LOG_VARS_MAX;
    for (uint32_t i = 0; i < nvars; i++) {
        const struct xrf_log_var *v = &meta->vars[i];
        const struct xrf_logfile_type *t = xrf_logfile_type_of(v->type);
        /* VAR_NAME without its comma for the first variable */
        put(&o, VAR_NAME + (i == 0), sizeof VAR_NAME - 1 - (i == 0));
        put_string(&o, v->name, strnlen(v->name, XRF_NAME_MAX));
        putf(&o, VAR_REST, (int)v->type, t ? t->dtype : "?", (int)v->offset);
    }
    put(&o, TAIL, sizeof TAIL - 1);
    size_t json = (size_t)(o.p - (buf + XRF_LOGFILE_PREFIX_SIZE));
    size_t total = (XRF_LOGFILE_PREFIX_SIZE + json + XRF_LOGFILE_ALIGN - 1) / XRF_LOGFILE_ALIGN *
                   XRF_LOGFILE_ALIGN;
    if (o.full || total > cap)
        return -ENOSPC;
    memset(o.p, 0, total - XRF_LOGFILE_PREFIX_SIZE - json);
    uint32_t words[2] = {(uint32_t)json, stride};
    memcpy(buf, xrf_logfile_magic, XRF_LOGFILE_MAGIC_SIZE);
    /* Little-endian on every target rt_core supports (x86-64, the Pi's aarch64). */
    memcpy(buf + XRF_LOGFILE_JSON_LEN_OFFSET, &words[0], 4);
    memcpy(buf + XRF_LOGFILE_STRIDE_OFFSET, &words[1], 4);
    return (int)total;
}
