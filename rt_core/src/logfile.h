// The in-band writer of the self-describing log file (docs/logging/file-format.md).
#pragma once

#include <cstdint>

#include "xrf/channels.h"

namespace xrf
{

struct LogSink;

// Opens (or switches to) the file named by `meta` when its generation changed, writes the
// segment header, then appends every complete record in `ring` (slots at `slots`). `final` also
// fsyncs. One call per channel: the logger's (log_meta/log_ring), the timing records.
void logfile_drain(const xrf_shm *shm, xrf_log_meta *meta, xrf_ring *ring, const void *slots,
                   LogSink *sink, const char *program, bool final);
void logfile_close(LogSink *sink);

// What to add to a failed open's message: " (only the run folder is writable)" for a
// permission or read-only error under the appliance (XRF_LOG_DIR set), else "".
const char *logfile_write_hint(int err);

} // namespace xrf
