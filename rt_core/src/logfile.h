// The in-band writer of the self-describing log file (docs/logging/file-format.md).
#pragma once

#include <cstdint>

#include "xrf/channels.h"

namespace xrf
{

struct LogSink;

// Opens (or switches to) the file named by `meta` when its generation changed, writes the
// segment header, then appends every complete record in `ring` (slots at `slots`, `capacity`
// bytes of them). `final` also fsyncs. One call per channel: the logger's (log_meta/log_ring),
// the timing records. The layout is taken with xrf_log_meta_check, as the appliance's host
// writer takes it: one reader of the rings for every side.
void logfile_drain(const xrf_shm *shm, const xrf_log_meta *meta, xrf_ring *ring, const void *slots,
                   uint32_t capacity, LogSink *sink, const char *program, bool final);
void logfile_close(LogSink *sink);

// What to add to a failed open's message: " (only the run folder is writable)" for a
// permission or read-only error under the appliance (XRF_LOG_DIR set), else "".
const char *logfile_write_hint(int err);

} // namespace xrf
