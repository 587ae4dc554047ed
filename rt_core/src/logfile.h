// The in-band writer of the self-describing log file (docs/logging/file-format.md).
#pragma once

#include <cstdint>

#include "xrf/channels.h"

namespace xrf {

// Opens (or switches to) the file named by shm->log_meta when its generation changed, writes the
// segment header, then appends every complete record in the log ring. `final` also fsyncs.
void logfile_drain(xrf_shm *shm, int *fd, uint64_t *generation, const char *program, bool final);

// Size in bytes of a variable of an XRF_LOG_* type, 0 for an unknown code.
int logfile_type_size(int32_t type);
const char *logfile_type_name(int32_t type);

} // namespace xrf
