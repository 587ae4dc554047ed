// Writes the log ring into the self-describing file format of docs/logging/file-format.md.
// Runs on the loop process's in-band helper thread (or, with XRF_LOG_WRITER=host, the appliance
// does the same from Python), so the loop never waits on a disk.
#include "logfile.h"
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

namespace xrf {

int logfile_type_size(int32_t type)
{
    switch (type) {
    case XRF_LOG_BOOL:
    case XRF_LOG_CHAR:
        return 1;
    case XRF_LOG_INT:
    case XRF_LOG_FLOAT:
        return 4;
    case XRF_LOG_DOUBLE:
    case XRF_LOG_LONG_INT:
        return 8;
    default:
        return 0;
    }
}

const char *logfile_type_name(int32_t type)
{
    switch (type) {
    case XRF_LOG_BOOL: return "bool";
    case XRF_LOG_CHAR: return "char";
    case XRF_LOG_INT: return "int32";
    case XRF_LOG_FLOAT: return "float32";
    case XRF_LOG_DOUBLE: return "float64";
    case XRF_LOG_LONG_INT: return "int64";
    default: return "?";
    }
}

const char *logfile_write_hint(int err)
{
    // Under the appliance the loop may write in its run folder only (a mount namespace covers
    // the rest): say so, or the student hunts for a permission problem that is by design.
    const char *dir = std::getenv("XRF_LOG_DIR");
    if (dir && *dir && (err == EROFS || err == EACCES || err == EPERM))
        return " (only the run folder is writable)";
    return "";
}

namespace {

void jsonString(std::string &out, const char *s)
{
    out += '"';
    for (; *s; s++) {
        unsigned char c = (unsigned char)*s;
        if (c == '"' || c == '\\') {
            out += '\\';
            out += (char)c;
        } else if (c < 0x20) {
            char buf[8];
            std::snprintf(buf, sizeof buf, "\\u%04x", c);
            out += buf;
        } else {
            out += (char)c;
        }
    }
    out += '"';
}

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

// One segment header: magic, JSON length, record stride, the JSON, zero padding to 8 bytes.
bool writeHeader(int fd, const xrf_shm *shm, const xrf_log_meta &m, uint32_t stride, const char *program)
{
    struct timespec wall, mono;
    clock_gettime(CLOCK_REALTIME, &wall);
    clock_gettime(CLOCK_MONOTONIC, &mono);
    std::string j = "{\"format\":\"xrflog\",\"version\":1,\"program\":";
    jsonString(j, program);
    j += ",\"project\":";
    jsonString(j, envOr("XRF_PROJECT", ""));
    j += ",\"build\":";
    jsonString(j, envOr("XRF_BUILD_ID", ""));
    j += ",\"run\":";
    jsonString(j, envOr("XRF_RUN_ID", ""));
    char buf[256];
    std::snprintf(buf, sizeof buf,
                  ",\"pid\":%d,\"cycle_freq\":%u,\"start_unix_ns\":%lld,\"start_mono_ns\":%lld,"
                  "\"record_header\":[[\"seq\",\"uint64\"],[\"cycle\",\"uint64\"],[\"t_ns\",\"int64\"]],"
                  "\"record_size\":%u,\"variables\":[",
                  (int)shm->info.pid, shm->info.cycle_freq,
                  (long long)wall.tv_sec * 1000000000LL + wall.tv_nsec,
                  (long long)mono.tv_sec * 1000000000LL + mono.tv_nsec, m.record_size);
    j += buf;
    for (uint32_t i = 0; i < m.nvars && i < XRF_LOG_VARS_MAX; i++) {
        char name[XRF_NAME_MAX + 1];
        std::memcpy(name, m.vars[i].name, XRF_NAME_MAX);
        name[XRF_NAME_MAX] = '\0';
        j += i ? ",{\"name\":" : "{\"name\":";
        jsonString(j, name);
        std::snprintf(buf, sizeof buf, ",\"type\":%d,\"dtype\":\"%s\",\"offset\":%d}",
                      m.vars[i].type, logfile_type_name(m.vars[i].type), m.vars[i].offset);
        j += buf;
    }
    j += "]}\n";
    uint8_t head[16] = {'X', 'R', 'F', 'L', 'O', 'G', '1', '\n'};
    uint32_t jlen = (uint32_t)j.size();
    std::memcpy(head + 8, &jlen, 4);   // little-endian on every target we support
    std::memcpy(head + 12, &stride, 4);
    size_t pad = (8 - (16 + j.size()) % 8) % 8;
    j.append(pad, '\0');
    return writeAll(fd, head, sizeof head) && writeAll(fd, j.data(), j.size());
}

} // namespace

void logfile_drain(const xrf_shm *shm, xrf_log_meta *meta, xrf_ring *ring, const void *slots,
                   LogSink *sink, const char *program, bool final)
{
    xrf_log_meta &m = *meta;
    if (__atomic_load_n(&m.ready, __ATOMIC_ACQUIRE) == 0)
        return;
    uint64_t gen = __atomic_load_n(&m.generation, __ATOMIC_ACQUIRE);
    if (gen != sink->generation) {
        logfile_close(sink);
        sink->generation = gen;
        char path[XRF_PATH_MAX + 1];
        std::memcpy(path, m.path, XRF_PATH_MAX);
        path[XRF_PATH_MAX] = '\0';
        mkdirParents(path);
        sink->fd = open(path, O_WRONLY | O_CREAT | O_APPEND | O_CLOEXEC, m.file_mode ? m.file_mode : 0644);
        if (sink->fd < 0 || !writeHeader(sink->fd, shm, m, ring->slot_size, program)) {
            int err = errno;
            std::fprintf(stderr, "xrf: cannot write the log file %s: %s%s; logging stops\n", path,
                         std::strerror(err), logfile_write_hint(err));
            if (sink->fd >= 0)
                close(sink->fd);
            sink->fd = -1;
        } else {
            sink->reported = false;
        }
    }
    uint32_t n = 0;
    const void *run;
    while ((run = xrf_spsc_peek_run(ring, slots, &n)) != nullptr) {
        if (sink->fd >= 0 && !writeAll(sink->fd, run, (size_t)n * ring->slot_size)) {
            if (!sink->reported)
                std::fprintf(stderr, "xrf: writing the log file failed (%s); logging stops, the "
                                     "loop goes on\n", std::strerror(errno));
            sink->reported = true;
            close(sink->fd);
            sink->fd = -1;
        }
        // Consumed either way: a dead disk must not turn into a full ring that hides the cause.
        xrf_spsc_release_n(ring, n);
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
