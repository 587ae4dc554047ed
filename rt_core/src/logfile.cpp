// Writes the log ring into the self-describing file format of docs/logging/file-format.md.
// Runs on the loop process's in-band helper thread (or, with XRF_LOG_WRITER=host, the appliance
// does the same from Python), so the loop never waits on a disk.
#include "logfile.h"
#include "xrf/logformat.h"
#include "xrf/runtime.hpp"

#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fcntl.h>
#include <string>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

namespace xrf
{

const char *logfile_write_hint(int err)
{
    // Under the appliance the loop may write in its run folder only (a mount namespace covers
    // the rest): say so, or the student hunts for a permission problem that is by design.
    const char *dir = std::getenv("XRF_LOG_DIR");
    if (dir && *dir && (err == EROFS || err == EACCES || err == EPERM))
        return " (only the run folder is writable)";
    return "";
}

namespace
{

const char *envOr(const char *name, const char *fallback)
{
    const char *v = std::getenv(name);
    return v && *v ? v : fallback;
}

int mkdirParents(const char *path)
{
    std::string p(path);
    for (size_t i = 1; i < p.size(); i++) {
        if (p[i] != '/')
            continue;
        std::string dir = p.substr(0, i);
        if (mkdir(dir.c_str(), 0775) != 0 && errno != EEXIST)
            return -errno;
    }
    return 0;
}

bool writeAll(int fd, const void *data, size_t n)
{
    const char *p = static_cast<const char *>(data);
    while (n > 0) {
        ssize_t w = write(fd, p, n);
        if (w < 0 && errno == EINTR)
            continue;
        if (w <= 0)
            return false;
        p += w;
        n -= (size_t)w;
    }
    return true;
}

// One segment header (xrf/logformat.h composes it; the appliance's host writer calls the same
// function), formatted into the sink's own buffer: the helper allocates nothing per file.
bool writeHeader(int fd, LogSink *sink, const xrf_shm *shm, const xrf_log_meta &m, uint32_t stride,
                 const char *program)
{
    struct timespec wall, mono;
    clock_gettime(CLOCK_REALTIME, &wall);
    clock_gettime(CLOCK_MONOTONIC, &mono);
    xrf_logfile_ident id{};
    id.program = program;
    id.project = envOr("XRF_PROJECT", "");
    id.build = envOr("XRF_BUILD_ID", "");
    id.run = envOr("XRF_RUN_ID", "");
    id.pid = shm->info.pid;
    id.cycle_freq = shm->info.cycle_freq;
    id.start_unix_ns = (int64_t)wall.tv_sec * 1000000000LL + wall.tv_nsec;
    id.start_mono_ns = (int64_t)mono.tv_sec * 1000000000LL + mono.tv_nsec;
    int n = xrf_logfile_header(sink->header, sizeof sink->header, &id, &m, stride);
    if (n < 0) {
        errno = -n; // the caller reports errno (an XRF_PROJECT/XRF_BUILD_ID/XRF_RUN_ID too long)
        return false;
    }
    return writeAll(fd, sink->header, (size_t)n);
}

} // namespace

void logfile_drain(const xrf_shm *shm, const xrf_log_meta *meta, xrf_ring *ring, const void *slots,
                   uint32_t capacity, LogSink *sink, const char *program, bool final)
{
    if (__atomic_load_n(&meta->ready, __ATOMIC_ACQUIRE) == 0)
        return;
    uint64_t gen = __atomic_load_n(&meta->generation, __ATOMIC_ACQUIRE);
    if (gen != sink->generation) {
        logfile_close(sink);
        int rc = xrf_log_meta_check(meta, ring, capacity, &sink->meta, &sink->geom, &sink->tail);
        if (rc == -EAGAIN)
            return; // published meanwhile: taken at the next drain
        sink->generation = rc == 0 ? sink->meta.generation : gen;
        sink->layout_ok = rc == 0;
        if (rc != 0) {
            std::fprintf(stderr, "xrf: the log layout in the shared memory is not one the logger "
                                 "publishes (overwritten?); logging stops\n");
            return;
        }
        const xrf_log_meta &m = sink->meta;
        mkdirParents(m.path);
        sink->fd = open(m.path, O_WRONLY | O_CREAT | O_APPEND | O_CLOEXEC,
                        m.file_mode ? m.file_mode : 0644);
        if (sink->fd < 0 || !writeHeader(sink->fd, sink, shm, m, sink->geom.slot_size, program)) {
            int err = errno;
            std::fprintf(stderr, "xrf: cannot write the log file %s: %s%s; logging stops\n", m.path,
                         std::strerror(err), logfile_write_hint(err));
            if (sink->fd >= 0)
                close(sink->fd);
            sink->fd = -1;
        } else {
            sink->reported = false;
        }
    }
    if (!sink->layout_ok)
        return;
    const void *run = nullptr;
    int n;
    while ((n = xrf_spsc_peek_run_g(ring, &sink->geom, slots, sink->tail, &run)) > 0) {
        if (sink->fd >= 0 && !writeAll(sink->fd, run, (size_t)n * sink->geom.slot_size)) {
            if (!sink->reported)
                std::fprintf(stderr,
                             "xrf: writing the log file failed (%s); logging stops, the "
                             "loop goes on\n",
                             std::strerror(errno));
            sink->reported = true;
            close(sink->fd);
            sink->fd = -1;
        }
        // Consumed either way: a dead disk must not turn into a full ring that hides the cause.
        xrf_spsc_release_g(ring, &sink->tail, (uint32_t)n);
    }
    if (final && sink->fd >= 0)
        fsync(sink->fd);
}

void logfile_close(LogSink *sink)
{
    if (sink->fd >= 0) {
        fsync(sink->fd);
        close(sink->fd);
        sink->fd = -1;
    }
}

} // namespace xrf
