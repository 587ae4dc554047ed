// XenoFileHandler and XenoFrtLogger.
#include "XenoFileHandler.hpp"
#include "XenoFrtLogger.hpp"

#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>
#include <vector>

#include "logfile.h"
#include "xrf/logformat.h"
#include "xrf/runtime.hpp"
#include "channels_inline.h" // the per-cycle handoffs, inlined (issue 30 item 5)

namespace
{

// A name with the run folder as its root: "." and empty parts dropped, ".." never climbing
// above the root (as in a chroot, "/.." is "/"). "/home/x/logs/log" -> "home/x/logs/log".
std::string underRunFolder(const std::string &name)
{
    std::vector<std::string> parts;
    size_t i = 0;
    while (i <= name.size()) {
        size_t j = name.find('/', i);
        if (j == std::string::npos)
            j = name.size();
        std::string part = name.substr(i, j - i);
        if (part == "..") {
            if (!parts.empty())
                parts.pop_back();
        } else if (!part.empty() && part != ".") {
            parts.push_back(part);
        }
        i = j + 1;
    }
    std::string out;
    for (const std::string &p : parts)
        out += (out.empty() ? "" : "/") + p;
    return out;
}

int makeParents(const char *path)
{
    std::string p(path);
    for (size_t i = 1; i < p.size(); i++) {
        if (p[i] == '/' && mkdir(p.substr(0, i).c_str(), 0775) != 0 && errno != EEXIST)
            return -errno;
    }
    return 0;
}

} // namespace

XenoFileHandler::XenoFileHandler(bool add_timestamp, const std::string &name,
                                 const std::string &type, mode_t mode)
    : mode_(mode)
{
    std::string ext = type;
    if (!ext.empty() && ext[0] == '.')
        ext.erase(0, 1);
    std::string base = name;
    if (add_timestamp) {
        std::time_t now = std::time(nullptr);
        std::tm tm{};
        localtime_r(&now, &tm);
        char stamp[32];
        std::strftime(stamp, sizeof stamp, "_%y%m%d_%H%M%S", &tm);
        base += stamp;
    }
    if (!ext.empty())
        base += "." + ext;
    // Under the appliance (XRF_LOG_DIR = the run folder) every name lands in the run folder with
    // the same layout, absolute ones included: XRF2 students write to /home/<name>/logs/...,
    // which is not theirs on a shared bench, and the run's downloads list the run folder only.
    // Said once here, at set-up, so the student knows where to look.
    const char *dir = std::getenv("XRF_LOG_DIR");
    std::string path = base;
    if (dir && *dir) {
        std::string rel = underRunFolder(base);
        path = std::string(dir) + "/" + rel;
        std::printf("xrf: log %s -> %s in the run folder\n", base.c_str(), rel.c_str());
    }
    if (path.size() >= sizeof path_) {
        std::fprintf(stderr,
                     "xrf: the log file name %s is longer than %zu characters; not logged\n",
                     path.c_str(), sizeof path_ - 1);
        path.clear();
    }
    std::snprintf(path_, sizeof path_, "%s", path.c_str());
    const char *writer = std::getenv("XRF_LOG_WRITER");
    if (path_[0] != '\0' && !(writer && std::strcmp(writer, "host") == 0)) {
        // This process writes the file: find out now, at set-up, whether it can (XRF2 opened it
        // here too). The host writer reports its own failures in the monitor.
        makeParents(path_);
        int fd = open(path_, O_WRONLY | O_CREAT | O_APPEND | O_CLOEXEC, mode_);
        if (fd < 0)
            std::fprintf(stderr, "xrf: cannot write the log file %s: %s%s\n", path_,
                         std::strerror(errno), xrf::logfile_write_hint(errno));
        else
            close(fd);
    }
    std::fflush(stdout);
}

XenoFrtLogger::XenoFrtLogger(XenoFileHandler &file, void *data) : file_(file), data_(data) {}

int XenoFrtLogger::addVariable(const char *name, int type)
{
    const xrf_logfile_type *t = xrf_logfile_type_of(type);
    const int size = t ? (int)t->size : 0;
    if (size == 0 || nvars_ >= max_variables || initialised_ || name == nullptr)
        return -1;
    Var &v = vars_[nvars_];
    std::snprintf(v.name, sizeof v.name, "%s", name);
    v.type = type;
    v.offset = (int)record_size_;
    record_size_ += (uint32_t)size;
    nvars_++;
    return 0;
}

int XenoFrtLogger::initialise()
{
    // Idempotent: a reset re-enters initialising, and XRF2 then wrote a second header.
    if (initialised_)
        return 0;
    if (nvars_ == 0 || data_ == nullptr)
        return -1;
    initialised_ = true;
    publish();
    return 0;
}

// Hands the layout and file name to whoever writes the file, once the run's shm exists.
bool XenoFrtLogger::publish()
{
    if (published_)
        return true;
    xrf::Runtime &rt = xrf::Runtime::instance();
    xrf_shm *shm = rt.shm();
    if (shm == nullptr)
        return false;
    xrf_log_meta &m = shm->log_meta;
    uint32_t slot_size = 0;
    uint32_t slots = xrf_log_slots_for(record_size_, XRF_LOG_RING_BYTES, &slot_size);
    m.nvars = (uint32_t)nvars_;
    m.record_size = record_size_;
    m.file_mode = (uint32_t)file_.mode();
    std::snprintf(m.path, sizeof m.path, "%s", file_.path());
    for (int i = 0; i < nvars_; i++) {
        std::memcpy(m.vars[i].name, vars_[i].name, sizeof m.vars[i].name);
        m.vars[i].type = vars_[i].type;
        m.vars[i].offset = vars_[i].offset;
    }
    xrf_ring_init(&shm->log_ring, slots, slot_size);
    __atomic_store_n(&m.generation, m.generation + 1, __ATOMIC_RELEASE);
    __atomic_store_n(&m.ready, 1u, __ATOMIC_RELEASE);
    published_ = true;
    return true;
}

int XenoFrtLogger::start()
{
    if (!initialised_)
        return -1;
    started_ = true;
    return 0;
}

int XenoFrtLogger::stop()
{
    started_ = false;
    return 0;
}

int XenoFrtLogger::log()
{
    if (!started_)
        return -1;
    if (!published_ && !publish())
        return -1;
    xrf::Runtime &rt = xrf::Runtime::instance();
    xrf_shm *shm = rt.shm();
    const uint64_t seq = seq_++; // counts lost records too: gaps stay visible in the file
    auto *slot = static_cast<xrf_slot_hdr *>(xrf_spsc_begin_inline(&shm->log_ring, shm->log_data));
    if (slot == nullptr)
        return -2;
    slot->seq = seq;
    slot->cycle = rt.cycle();
    slot->t_ns = rt.cycleStart();
    std::memcpy(slot + 1, data_, record_size_);
    xrf_spsc_commit_inline(&shm->log_ring, slot);
    return 0;
}
