/*
 * xrf/logformat.h — the one definition of the xrflog file format's segment header
 * (docs/logging/file-format.md): the magic, the fixed prefix's layout, the variable type codes
 * with their names, and the function that formats a segment header.
 *
 * Two writers produce segment headers: the loop process's in-band helper thread (logfile.cpp,
 * XRF_LOG_WRITER=process) and the appliance's host writer (xrflab/logs/live.py, through the cffi
 * binding, XRF_LOG_WRITER=host); the reader (xrflab/logs/reader.py) takes the magic, the layout
 * and the type table from here too. A file must not depend on which side wrote it, so neither side
 * composes a header of its own: both call xrf_logfile_header() with the same inputs.
 *
 * API style as libevl: xrf_ prefix, a byte count or -errno. The formatter never allocates (the
 * caller owns the buffer), so it is safe on any thread; it runs on the in-band helper, not on the
 * loop thread, because a header is written when a log file is opened, not each cycle.
 */
#ifndef XRF_LOGFORMAT_H
#define XRF_LOGFORMAT_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* The shm's description of a log channel (xrf/channels.h); only pointed to here. */
struct xrf_log_meta;

/* cffi-begin */
/* Variable type codes: XRF2's (its .bin header and XenoFrtLogger's enums use the same numbers),
 * kept so that an XRF2 program's addVariable() calls mean what they meant there. */
#define XRF_LOG_BOOL 1
#define XRF_LOG_CHAR 2
#define XRF_LOG_INT 3
#define XRF_LOG_FLOAT 4
#define XRF_LOG_DOUBLE 5
#define XRF_LOG_LONG_INT 6
#define XRF_LOG_NTYPES 6 /* codes are 1..XRF_LOG_NTYPES, in xrf_logfile_types[] in that order */

/* The JSON header's "version"; a reader refuses others (the layout below is version 1's). */
#define XRF_LOGFILE_VERSION 1

/* A segment's fixed prefix: magic, then J (uint32 LE, the JSON's length, its '\n' included),
 * then S (uint32 LE, the record stride), then the JSON, zero-padded so that the records start
 * at a multiple of XRF_LOGFILE_ALIGN from the segment's first byte (8: every record field is
 * then naturally aligned in a mapped file). */
#define XRF_LOGFILE_MAGIC_SIZE 8
#define XRF_LOGFILE_JSON_LEN_OFFSET 8
#define XRF_LOGFILE_STRIDE_OFFSET 12
#define XRF_LOGFILE_PREFIX_SIZE 16
#define XRF_LOGFILE_ALIGN 8

/* Longest project, build, run or program text a header carries (bytes, NUL excluded). With
 * it, every header fits XRF_LOGFILE_HEADER_MAX, so a writer can own a fixed buffer. */
#define XRF_LOGFILE_TEXT_MAX 255
/* Bound on a whole segment header (prefix, JSON, padding): XRF_LOG_VARS_MAX variables with
 * names of XRF_NAME_MAX bytes that all need \u escapes, four texts of XRF_LOGFILE_TEXT_MAX
 * likewise, every number at its widest (logformat.c checks the sum at compile time). */
#define XRF_LOGFILE_HEADER_MAX 57344

/* "XRFLOG1\n": starts every segment (and so every xrflog file); no NUL after it. */
extern const char xrf_logfile_magic[XRF_LOGFILE_MAGIC_SIZE];

/* One variable type: the one table of names every writer and reader uses. */
struct xrf_logfile_type {
    int32_t code;        /* XRF_LOG_* */
    uint32_t size;       /* bytes in the packed record */
    const char *name;    /* XRF2's (C) name: "bool", "char", "int", "float", "double", "long int" */
    const char *dtype;   /* the header's "dtype": "bool", "char", "int32", "float32", ... */
    const char *typestr; /* NumPy array-interface type string ("<i4"): a NumPy reader needs no
                            table of its own. char is one raw byte ("|S1"): C's char is signed on
                            x86 and unsigned on ARM, so no signedness is claimed. */
};
extern const struct xrf_logfile_type xrf_logfile_types[XRF_LOG_NTYPES];

/* The entry of `code`, or NULL for a code no writer accepts. */
const struct xrf_logfile_type *xrf_logfile_type_of(int32_t code);

/* Who wrote a segment and when it started: the header's fields other than the log layout.
 * NULL texts are written as "". */
struct xrf_logfile_ident {
    const char *program;   /* the loop's program name (xrf_info.program) */
    const char *project;   /* XRF_PROJECT */
    const char *build;     /* XRF_BUILD_ID */
    const char *run;       /* XRF_RUN_ID */
    int32_t pid;           /* the loop process (xrf_info.pid) */
    uint32_t cycle_freq;   /* xrf_info.cycle_freq */
    int64_t start_unix_ns; /* CLOCK_REALTIME when the segment was opened */
    int64_t start_mono_ns; /* CLOCK_MONOTONIC at the same moment: turns t_ns into wall time */
};

/* Formats the segment header for the log channel `meta` (its record_size and variables, as the
 * loop published them) whose records are `stride` bytes apart, into buf[0..cap). Returns its
 * length (a multiple of XRF_LOGFILE_ALIGN), -EINVAL (NULL argument), -ENAMETOOLONG (a text
 * longer than XRF_LOGFILE_TEXT_MAX) or -ENOSPC (cap too small; XRF_LOGFILE_HEADER_MAX always
 * suffices). Texts and names are JSON-escaped; bytes that are not UTF-8 become U+FFFD, so the
 * header always parses, whatever a (student's) variable name holds. A type code outside the
 * table is written with dtype "?" (the reader then names the variable and the code). */
int xrf_logfile_header(char *buf, size_t cap, const struct xrf_logfile_ident *id,
                       const struct xrf_log_meta *meta, uint32_t stride);
/* cffi-end */

#ifdef __cplusplus
}
#endif

#endif
