// XenoFileHandler and XenoFrtLogger.
#include "XenoFileHandler.hpp"
#include "XenoFrtLogger.hpp"

#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>

#include "logfile.h"
#include "xrf/runtime.hpp"

XenoFileHandler::XenoFileHandler(bool add_timestamp, const std::string &name,
                                 const std::string &type, mode_t mode)
    : mode_(mode)
{
    std::string ext = type;
    if (!ext.empty() && ext[0] == '.')
        ext.erase(0, 1);
    std::string base = name;
    const char *dir = std::getenv("XRF_LOG_DIR");
    if (dir && *dir && !base.empty() && base[0] != '/')
        base = std::string(dir) + "/" + base;
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
    std::snprintf(path_, sizeof path_, "%s", base.c_str());
}

XenoFrtLogger::XenoFrtLogger(XenoFileHandler &file, void *data) : file_(file), data_(data) {}

int XenoFrtLogger::addVariable(const char *name, int type)
{
    const int size = xrf::logfile_type_size(type);
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
    auto *slot = static_cast<xrf_slot_hdr *>(xrf_spsc_begin(&shm->log_ring, shm->log_data));
    if (slot == nullptr)
        return -2;
    slot->seq = seq;
    slot->cycle = rt.cycle();
    slot->t_ns = rt.cycleStart();
    std::memcpy(slot + 1, data_, record_size_);
    xrf_spsc_commit(&shm->log_ring, slot);
    return 0;
}
