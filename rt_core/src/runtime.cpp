// The per-process runtime (xrf/runtime.hpp).
#include "xrf/runtime.hpp"

#include <cerrno>
#include <csignal>
#include <sched.h>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#include "channels_inline.h" // the per-cycle handoffs, inlined (issue 30 item 5)
#include "hist_inline.h"
#include "logfile.h"
#include "params_registry.h"
#include "unprivileged.h"
#include "xrf/plants.h"
#include "xrf/sim.h"

namespace xrf
{

namespace
{

volatile sig_atomic_t g_signal_stop = 0;

void onStopSignal(int)
{
    g_signal_stop = 1;
}

void copyString(char *dst, size_t n, const char *src)
{
    if (n == 0)
        return;
    std::snprintf(dst, n, "%s", src ? src : "");
}

bool envString(const char *name, char *dst, size_t n)
{
    const char *v = std::getenv(name);
    if (v == nullptr || v[0] == '\0')
        return false;
    copyString(dst, n, v);
    return true;
}

// Parses an integer variable; prints and returns false when it is set but malformed.
bool envLong(const char *name, long lo, long hi, long *out)
{
    const char *v = std::getenv(name);
    if (v == nullptr || v[0] == '\0')
        return true;
    char *end = nullptr;
    errno = 0;
    long x = std::strtol(v, &end, 10);
    if (errno != 0 || end == v || *end != '\0' || x < lo || x > hi) {
        std::fprintf(stderr, "xrf: %s=%s is not a whole number in %ld..%ld\n", name, v, lo, hi);
        return false;
    }
    *out = x;
    return true;
}

// A (counter, CLOCK_MONOTONIC) pair read as close together as this thread gets: of a few tries,
// the one whose clock read took the fewest ticks, the counter taken at its middle.
void counterClockPair(uint64_t *counter, int64_t *ns)
{
    uint64_t best = UINT64_MAX;
    for (int i = 0; i < 5; i++) {
        struct timespec ts;
        const uint64_t a = xrf_cycle_counter();
        clock_gettime(CLOCK_MONOTONIC, &ts);
        const uint64_t b = xrf_cycle_counter();
        if (b - a < best) {
            best = b - a;
            *counter = a + (b - a) / 2;
            *ns = (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
        }
    }
}

} // namespace

int Options::fromEnvironment()
{
    bool ok = true;
    envString("XRF_SHM", shm_name, sizeof shm_name);
    envString("XRF_BACKEND", backend, sizeof backend);
    envString("XRF_TRANSPORT", transport, sizeof transport);
    envString("XRF_SIM", sim, sizeof sim);
    envString("XRF_SIM_FAULTS", sim_faults, sizeof sim_faults);
    envString("XRF_SPI_DEVICE", spi_device, sizeof spi_device);
    envString("XRF_LOG_DIR", log_dir, sizeof log_dir);
    long x;
    x = spi_speed;
    ok &= envLong("XRF_SPI_SPEED", 1000, 100000000, &x);
    spi_speed = (uint32_t)x;
    x = 0;
    ok &= envLong("XRF_FREQ", 100, 10000, &x);
    freq_override = (unsigned)x;
    x = cpu;
    ok &= envLong("XRF_CPU", -1, 1023, &x);
    cpu = (int)x;
    x = -1;
    ok &= envLong("XRF_SHM_FD", -1, 1 << 20, &x);
    shm_fd = (int)x;
    x = priority;
    ok &= envLong("XRF_PRIO", -1, 99, &x);
    priority = (int)x;
    x = 0;
    ok &= envLong("XRF_HOST_TIMEOUT_MS", 0, 600000, &x);
    host_timeout_ms = (uint32_t)x;
    x = 0;
    ok &= envLong("XRF_MAX_CYCLES", 0, 0x7fffffffffffffffL, &x);
    max_cycles = (uint64_t)x;
    const char *v = std::getenv("XRF_PWM_LIMIT");
    if (v && *v) {
        char *end = nullptr;
        double d = std::strtod(v, &end);
        if (end == v || *end != '\0' || d < 0.0 || d > 1.0) {
            std::fprintf(stderr, "xrf: XRF_PWM_LIMIT=%s must be a fraction 0..1 (0.2 = 20 %%)\n",
                         v);
            ok = false;
        } else {
            pwm_limit = d;
        }
    }
    v = std::getenv("XRF_LOG_WRITER");
    if (v && *v) {
        if (std::strcmp(v, "host") == 0)
            log_writer = XRF_LOG_WRITER_HOST;
        else if (std::strcmp(v, "process") == 0)
            log_writer = XRF_LOG_WRITER_PROCESS;
        else {
            std::fprintf(stderr, "xrf: XRF_LOG_WRITER=%s: use 'process' or 'host'\n", v);
            ok = false;
        }
    }
    v = std::getenv("XRF_HOST_TIMEOUT_ACTION");
    if (v && *v) {
        int32_t action = xrf_host_lost_action_parse(v);
        if (action >= 0)
            host_timeout_action = (uint32_t)action;
        else {
            std::fprintf(stderr, "xrf: XRF_HOST_TIMEOUT_ACTION=%s: use", v);
            for (int32_t a = 0; a < XRF_HOST_LOST_ACTION_COUNT; a++)
                std::fprintf(stderr, "%s %s", a ? "," : "", xrf_host_lost_action_name(a));
            std::fprintf(stderr, "\n");
            ok = false;
        }
    }
    v = std::getenv("XRF_VIRTUAL_TIME");
    if (v && *v && std::strcmp(v, "0") != 0) {
        if (std::strcmp(v, "1") == 0)
            virtual_time = 1;
        else if (std::strcmp(v, "hold") == 0)
            virtual_time = 2;
        else {
            std::fprintf(stderr, "xrf: XRF_VIRTUAL_TIME=%s: use 0, 1 or hold\n", v);
            ok = false;
        }
    }
    v = std::getenv("XRF_QUIET");
    quiet = v && *v && std::strcmp(v, "0") != 0;
    v = std::getenv("XRF_LOG_TIMING");
    log_timing = v && *v && std::strcmp(v, "0") != 0;
    if (std::strchr(shm_name, '/') != nullptr) {
        std::fprintf(stderr, "xrf: XRF_SHM=%s must be a plain name without '/'\n", shm_name);
        ok = false;
    }
    return ok ? 0 : -EINVAL;
}

Runtime *Runtime::self_ = nullptr;

Runtime &Runtime::create()
{
    // Made on first use, whichever static constructor (a student's global loop) asks first.
    static Runtime rt;
    self_ = &rt;
    return rt;
}

const Options &Runtime::options()
{
    if (!options_loaded_) {
        options_loaded_ = true;
        if (options_.fromEnvironment() != 0)
            std::exit(2); // a mistyped option must not silently run with defaults on a robot
    }
    return options_;
}

void Runtime::describe(unsigned write_decimator_freq, unsigned monitor_freq,
                       const char *ros2xeno_schema, uint32_t ros2xeno_size,
                       const char *xeno2ros_schema, uint32_t xeno2ros_size)
{
    write_decimator_freq_ = write_decimator_freq;
    monitor_freq_ = monitor_freq;
    ros2xeno_schema_ = ros2xeno_schema;
    ros2xeno_size_ = ros2xeno_size;
    xeno2ros_schema_ = xeno2ros_schema;
    xeno2ros_size_ = xeno2ros_size;
}

unsigned Runtime::effectiveFrequency(unsigned requested)
{
    unsigned f = options().freq_override ? options().freq_override : requested;
    return f;
}

void Runtime::setProgramName(const char *name)
{
    copyString(program_, sizeof program_, name);
}

xrf_ico_transport *Runtime::transport()
{
    if (transport_ != nullptr || transport_failed_)
        return transport_;
    const Options &o = options();
    const char *want = o.transport;
    if (std::strcmp(want, "auto") == 0) {
        // The first board's device decides (XRF_SPI_DEVICE may list one per board).
        char first[XRF_SPI_PATH_MAX];
        const size_t n = std::strcspn(o.spi_device, ",");
        copyString(first, sizeof first, o.spi_device);
        if (n < sizeof first)
            first[n] = '\0';
        want = access(first, F_OK) == 0 ? "spidev" : "sim";
    }
    int r = -EINVAL;
    if (std::strcmp(want, "sim") == 0) {
        int robot = xrf_sim_robot_from_name(o.sim);
        if (robot < 0) {
            char names[256];
            xrf_plant_names(names, sizeof names);
            std::fprintf(stderr, "xrf: XRF_SIM=%s: use one of %s\n", o.sim, names);
        } else {
            xrf_sim_faults faults;
            std::memset(&faults, 0, sizeof faults);
            r = xrf_sim_parse_faults(o.sim_faults, &faults);
            if (r != 0)
                std::fprintf(stderr, "xrf: XRF_SIM_FAULTS=%s is not a valid fault list\n",
                             o.sim_faults);
            else {
                // On the host's bench when it has room for the plant (setChannels refuses it
                // otherwise), else on the plant row's own.
                const uint32_t need = (uint32_t)xrf_plant_channels(robot);
                const int bench = host_channels_ >= need && host_channels_ <= XRF_MAX_CHANNELS
                                      ? (int)host_channels_
                                      : 0;
                r = xrf_sim_open_bench(robot, bench, &faults, 0.0, shm_ ? &shm_->sim : nullptr,
                                       &transport_);
            }
            if (r == 0 && shm_) /* the watcher's `hold` steps the plant on from there */
                xrf_sim_set_snapshot(transport_, &shm_->sim_snapshot);
        }
    } else if (std::strcmp(want, "spidev") == 0) {
        r = xrf_spidev_open(o.spi_device, o.spi_speed, &transport_);
    } else if (std::strcmp(want, "evl-spidev") == 0) {
        r = xrf_evl_spidev_open(o.spi_device, o.spi_speed, &transport_);
    } else {
        std::fprintf(stderr, "xrf: XRF_TRANSPORT=%s: use", want);
        for (int32_t t = 0; t < XRF_TRANSPORT_COUNT; t++)
            std::fprintf(stderr, "%s %s", t ? "," : "", xrf_transport_name(t));
        std::fprintf(stderr, " or auto\n");
    }
    if (r != 0 || transport_ == nullptr) {
        if (r != -EINVAL)
            std::fprintf(stderr, "xrf: cannot open the ico board (%s %s): %s\n", want,
                         std::strcmp(want, "sim") == 0 ? o.sim : o.spi_device, std::strerror(-r));
        transport_ = nullptr;
        transport_failed_ = true;
        return nullptr;
    }
    copyString(transport_name_, sizeof transport_name_, want);
    return transport_;
}

int Runtime::mapShm(int fd, const char *what, bool keep_fd)
{
    shm_size_ = sizeof(xrf_shm);
    void *p = mmap(nullptr, shm_size_, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
    if (!keep_fd)
        close(fd);
    if (p == MAP_FAILED) {
        int e = errno;
        std::fprintf(stderr, "xrf: cannot map shared memory %s: %s\n", what, std::strerror(e));
        return -e;
    }
    // The host that made the segment wrote the bench's channel count into it: kept across the
    // initialisation below (a count outside 1..XRF_MAX_CHANNELS is refused at enter()).
    host_channels_ = keep_fd ? static_cast<const xrf_shm *>(p)->channels : 0;
    // Touch every page now: the loop must not take a page fault on its first telemetry slot.
    std::memset(p, 0, shm_size_);
    shm_ = static_cast<xrf_shm *>(p);
    xrf_shm_init(shm_);
    return 0;
}

int Runtime::createShm()
{
    const Options &o = options();
    if (o.shm_fd >= 0) {
        // Made and sized by the appliance (a sealed memfd): mapped as it is, never resized.
        struct stat st;
        if (fstat(o.shm_fd, &st) != 0 || (size_t)st.st_size < sizeof(xrf_shm)) {
            std::fprintf(stderr, "xrf: XRF_SHM_FD=%d is not a segment of %zu bytes\n", o.shm_fd,
                         sizeof(xrf_shm));
            return -EINVAL;
        }
        // Kept open: it is the launcher's to give and the mapping's to hold, closing it gains
        // nothing (its seals, not its absence, keep the size fixed).
        return mapShm(o.shm_fd, "XRF_SHM_FD", true);
    }
    char path[XRF_NAME_MAX + 16];
    std::snprintf(path, sizeof path, "/%s", o.shm_name);
    int fd = shm_open(path, O_RDWR | O_CREAT | O_EXCL, 0660);
    if (fd < 0 && errno == EEXIST) {
        // A leftover of an earlier run is replaced, but never one whose loop is still alive.
        int old = shm_open(path, O_RDONLY, 0);
        if (old >= 0) {
            struct stat st;
            if (fstat(old, &st) == 0 && (size_t)st.st_size >= sizeof(xrf_shm)) {
                void *p = mmap(nullptr, sizeof(xrf_shm), PROT_READ, MAP_SHARED, old, 0);
                if (p != MAP_FAILED) {
                    const xrf_shm *prev = static_cast<const xrf_shm *>(p);
                    int32_t pid = prev->info.pid;
                    bool alive = prev->magic == XRF_SHM_MAGIC && prev->status.running && pid > 0 &&
                                 pid != getpid() && kill(pid, 0) == 0;
                    munmap(p, sizeof(xrf_shm));
                    if (alive) {
                        close(old);
                        std::fprintf(stderr,
                                     "xrf: another loop (pid %d) is running on shared memory '%s'; "
                                     "stop it or choose another name with XRF_SHM\n",
                                     (int)pid, o.shm_name);
                        return -EBUSY;
                    }
                }
            }
            close(old);
        }
        shm_unlink(path);
        fd = shm_open(path, O_RDWR | O_CREAT | O_EXCL, 0660);
    }
    if (fd < 0) {
        int e = errno;
        std::fprintf(stderr, "xrf: cannot create shared memory %s: %s\n", path, std::strerror(e));
        return -e;
    }
    fchmod(fd, 0660); // the umask must not make it world-writable nor unreadable for the group
    if (ftruncate(fd, (off_t)sizeof(xrf_shm)) != 0) {
        int e = errno;
        close(fd);
        std::fprintf(stderr, "xrf: cannot size shared memory %s: %s\n", path, std::strerror(e));
        return -e;
    }
    return mapShm(fd, path, false);
}

// The bench's channel count into the segment: the host's, else the simulated plant's (its row in
// plants.c), else one ico board. A simulated plant that needs more channels than the host's
// bench has is refused: its motors beyond the bench would be driven by nobody.
int Runtime::setChannels()
{
    const Options &o = options();
    const bool sim = transport_ != nullptr && std::strcmp(transport_name_, "sim") == 0;
    const int plant = sim ? xrf_plant_channels(xrf_sim_robot_from_name(o.sim)) : 0;
    uint32_t n = XRF_ICO_CHANNELS;
    if (host_channels_ != 0) {
        if (host_channels_ > XRF_MAX_CHANNELS) {
            std::fprintf(stderr, "xrf: the host's segment says %u channels, at most %d exist\n",
                         host_channels_, XRF_MAX_CHANNELS);
            return -EINVAL;
        }
        n = host_channels_;
        if (plant > 0 && (uint32_t)plant > n) {
            std::fprintf(stderr, "xrf: XRF_SIM=%s needs %d channels, the bench has %u\n", o.sim,
                         plant, n);
            return -EINVAL;
        }
    } else if (plant > 0) {
        n = (uint32_t)plant;
    }
    shm_->channels = n;
    return 0;
}

int Runtime::enter(unsigned cycle_freq)
{
    const Options &o = options();
    backend_ = o.virtual_time ? xrf_backend_virtual() : xrf_backend_by_name(o.backend);
    posix_ = backend_ != nullptr && backend_ == xrf_backend_by_name("posix");
    virtual_ = o.virtual_time != 0;
    if (backend_ == nullptr) {
        std::fprintf(stderr, "xrf: XRF_BACKEND=%s is not available in this build (have: posix%s)\n",
                     o.backend, xrf_backend_evl() ? ", evl" : "");
        return -EINVAL;
    }
    if (cycle_freq < 1 || cycle_freq > 100000) {
        std::fprintf(stderr, "xrf: cycle frequency %u Hz is out of range\n", cycle_freq);
        return -EINVAL;
    }
    // The stage timer's rate is measured across enter(), from here to before the thread goes
    // real-time (calibrateStageCounter). Simulated time keeps its own clock for stages too.
    const bool stage_counter = XRF_HAVE_CYCLE_COUNTER && !virtual_ && xrf_cycle_counter_invariant();
    uint64_t cal_c0 = 0;
    int64_t cal_t0 = 0;
    if (stage_counter)
        counterClockPair(&cal_c0, &cal_t0);
    if (program_[0] == '\0')
        copyString(program_, sizeof program_, program_invocation_short_name);
    // Before anything is mapped: under a memlock limit that cannot hold the channels (a normal
    // user's 8 MiB), locking is switched off with a warning instead of every mapping failing.
    const bool may_lock = fitMemoryLocking(sizeof(xrf_shm) + (16u << 20), o.quiet);
    int r = createShm();
    if (r != 0)
        return r;
    // Opened in-band, before the thread goes real-time. A board opened earlier (a constructor
    // that called ico_io.init()) keeps working, without the simulator's shared-memory mirror.
    if (transport_ == nullptr && !transport_failed_)
        transport();
    if (virtual_) {
        // A real robot moves in real time: simulated time exists only on the simulated board.
        if (transport_ == nullptr || std::strcmp(transport_name_, "sim") != 0) {
            std::fprintf(
                stderr,
                "xrf: XRF_VIRTUAL_TIME runs only on the simulated board (XRF_TRANSPORT=sim), "
                "not on %s\n",
                transport_name_[0] ? transport_name_ : "no board");
            return -EINVAL;
        }
        xrf_sim_set_clock(transport_, xrf_virtual_now_ns);
        shm_->vtime.active = 1;
        shm_->vtime.run_until = options_.virtual_time == 2 ? 1 : UINT64_MAX;
        xrf_backend_virtual_bind(shm_, &g_signal_stop);
    }

    r = setChannels();
    if (r != 0)
        return r;

    shm_->host_timeout_ms = o.host_timeout_ms;
    shm_->host_timeout_action = o.host_timeout_action;
    shm_->host_heartbeat_ns = 0;

    xrf_info &info = shm_->info;
    info.pid = (int32_t)getpid();
    info.cycle_freq = cycle_freq;
    info.write_decimator_freq = write_decimator_freq_;
    info.monitor_freq = monitor_freq_;
    info.ros2xeno_size = ros2xeno_size_;
    info.xeno2ros_size = xeno2ros_size_;
    info.cpu = o.cpu;
    // Ring the host at most once per millisecond: bounded wake-ups whatever the cycle rate.
    doorbell_period_ = cycle_freq > 1000 ? cycle_freq / 1000 : 1;
    info.doorbell_period_cycles = doorbell_period_;
    copyString(info.backend, sizeof info.backend, backend_->name);
    copyString(info.transport, sizeof info.transport, transport_name_);
    copyString(info.sim, sizeof info.sim, std::strcmp(transport_name_, "sim") == 0 ? o.sim : "");
    copyString(info.program, sizeof info.program, program_);
    copyString(info.ros2xeno_schema, sizeof info.ros2xeno_schema, ros2xeno_schema_);
    copyString(info.xeno2ros_schema, sizeof info.xeno2ros_schema, xeno2ros_schema_);
    shm_->log_meta.writer = (uint32_t)o.log_writer;
    if (o.log_timing) {
        // Beside the logger's file: in XRF_LOG_DIR, else the working directory (the appliance
        // writes it into the run's folder).
        char path[XRF_PATH_MAX + 32];
        int n = std::snprintf(path, sizeof path, "%s%scycle_timing.xrf", o.log_dir,
                              o.log_dir[0] ? "/" : "");
        if (n < 0 || n >= XRF_PATH_MAX) {
            std::fprintf(
                stderr,
                "xrf: XRF_LOG_DIR is too long for cycle_timing.xrf; timing is not logged\n");
        } else {
            xrf_ring_init(&shm_->timing_ring, XRF_TIMING_SLOTS, sizeof(xrf_timing_record));
            xrf_timing_meta_init(&shm_->timing_meta, (uint32_t)o.log_writer, path);
            timing_on_ = true;
        }
    }

    struct sigaction sa;
    std::memset(&sa, 0, sizeof sa);
    sa.sa_handler = onStopSignal;
    sigemptyset(&sa.sa_mask);
    sigaction(SIGINT, &sa, nullptr);
    sigaction(SIGTERM, &sa, nullptr);
    // stdout may be a pipe whose reader goes away (`xrf run | head`): an EPIPE, not a dead loop.
    std::signal(SIGPIPE, SIG_IGN);

    startHelper();
    loop_thread_ = pthread_self();
    // SIGINT/SIGTERM are taken by an in-band thread (the helper unblocks them), never by the
    // loop: a handler run on an EVL out-of-band thread demotes it. The handler only sets the
    // flag the loop reads each cycle. Without a helper nothing else could take them.
    if (helper_started_) {
        sigset_t stop_signals;
        sigemptyset(&stop_signals);
        sigaddset(&stop_signals, SIGINT);
        sigaddset(&stop_signals, SIGTERM);
        signals_blocked_ = pthread_sigmask(SIG_BLOCK, &stop_signals, &saved_sigmask_) == 0;
    }
    // Keep the CPUs out of deep idle states while the loop runs (what cyclictest does by
    // default): waking from them adds tens of microseconds at every 1 kHz wake-up. The request
    // lasts as long as the file stays open; without permission the loop runs anyway.
    dma_latency_fd_ = open("/dev/cpu_dma_latency", O_WRONLY | O_CLOEXEC);
    if (dma_latency_fd_ >= 0) {
        const int32_t zero = 0;
        if (write(dma_latency_fd_, &zero, sizeof zero) != (ssize_t)sizeof zero) {
            close(dma_latency_fd_);
            dma_latency_fd_ = -1;
        }
    }

    // The parameter table, before ready: a host reads it once it sees the loop ready.
    params::publish(&shm_->params, o.quiet);

    xrf_rt_config cfg;
    cfg.cpu = o.cpu;
    cfg.priority = o.priority;
    // Asked here, before the backend runs: after an EVL attach this call would demote the thread.
    int policy = SCHED_OTHER;
    sched_param sp{};
    pthread_getschedparam(pthread_self(), &policy, &sp);
    const bool main_chose_rt = policy == SCHED_FIFO || policy == SCHED_RR;
    if (cfg.priority < 0) {
        // A short main asks for nothing: make the loop real-time as an XRF2 main would. A main
        // that already chose SCHED_FIFO/RR keeps its choice (XRF_PRIO=0 keeps any policy).
        // A main whose SCHED_FIFO thread was refused (unprivileged.cpp) keeps asking for its priority.
        cfg.priority = main_chose_rt ? 0
                                     : (refusedThreadPriority() > 0 ? refusedThreadPriority()
                                                                    : kDefaultPriority);
    }
    cfg.lock_memory = may_lock ? 1 : 0;
    cfg.stack_prefault = 256 * 1024;
    // In-band still: the calibration may sleep (after an EVL attach that would demote the thread).
    if (stage_counter)
        calibrateStageCounter(cal_c0, cal_t0);
    // Printed before the backend's set-up: on EVL the set-up ends with stage-switch warnings on
    // (EVL_T_WOSS) and the thread out-of-band, so any write after it counts as a demotion.
    if (!o.quiet)
        std::fprintf(
            stderr,
            "xrf: loop '%s' at %u Hz, backend %s, board %s%s%s, shared memory /dev/shm/%s\n",
            program_, cycle_freq, backend_->name, transport_name_[0] ? transport_name_ : "none",
            info.sim[0] ? " " : "", info.sim, o.shm_name);
    r = backend_->thread_setup(&cfg, &rt_sched_);
    if (r != 0) {
        std::fprintf(stderr, "xrf: the %s backend could not set up the loop thread: %s\n",
                     backend_->name, std::strerror(-r));
        return r;
    }
    info.rt_sched = rt_sched_;
    info.priority = !rt_sched_ ? 0 : (cfg.priority > 0 ? cfg.priority : sp.sched_priority);

    xrf_status_write_begin_inline(&shm_->status);
    shm_->status.running = 1;
    shm_->status.end_reason = XRF_END_NONE;
    shm_->status.state = report_.state;
    xrf_status_write_end_inline(&shm_->status);
    xrf_shm_publish_ready(shm_);
    return 0;
}

bool Runtime::stopRequested() const
{
    if (g_signal_stop)
        return true;
    if (options_.max_cycles && cycles_ >= options_.max_cycles)
        return true;
    return stop_.load(std::memory_order_relaxed);
}

uint32_t Runtime::hostLostEdge(bool stale)
{
    host_lost_ = stale;
    if (!stale)
        return XRF_HOST_LOST_ACTION_IGNORE; // the host is back: the next loss acts again
    host_lost_count_++;
    return __atomic_load_n(&shm_->host_timeout_action, __ATOMIC_RELAXED);
}

// The stage timer's rate against CLOCK_MONOTONIC over at least 2 ms since (c0, t0): the pairs'
// uncertainty (tens of ns) is then 10^-5 of a stage time at most. A rate outside 1 MHz..20 GHz
// means the counter is not what xrf/cycle_counter.h assumes: stage times then come from now().
void Runtime::calibrateStageCounter(uint64_t c0, int64_t t0)
{
    constexpr int64_t kSpan = 2000000; // ns
    uint64_t c1 = 0;
    int64_t t1 = 0;
    counterClockPair(&c1, &t1);
    if (t1 - t0 < kSpan) {
        const int64_t until = t0 + kSpan;
        struct timespec ts = {(time_t)(until / 1000000000LL), (long)(until % 1000000000LL)};
        while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr) == EINTR) {}
        counterClockPair(&c1, &t1);
    }
    counter_mult_ = 0;
    if (c1 <= c0 || t1 <= t0)
        return;
    const double ns_per_tick = (double)(t1 - t0) / (double)(c1 - c0);
    if (!(ns_per_tick >= 0.05 && ns_per_tick <= 1000.0))
        return;
    counter_mult_ = (uint64_t)(ns_per_tick * 4294967296.0 + 0.5);
}

void Runtime::applyParams()
{
    params::take(&shm_->params, &params_seen_, cycles_);
}

void Runtime::endCycle(int64_t wake_ns, int64_t deadline_ns, int64_t end_ns, uint64_t skipped,
                       int64_t idle_ns)
{
    const uint64_t cycles = ++cycles_;
    missed_ += skipped;
    if (idle_ns > 0)
        idle_total_ += (uint64_t)idle_ns;
    const int64_t jitter = wake_ns - deadline_ns;
    if (timing_on_)
        recordTiming(jitter, end_ns - wake_ns, skipped);
    xrf_status *s = &shm_->status;
    xrf_status_write_begin_inline(s);
    s->state = report_.state;
    s->last_error = report_.last_error;
    // The command fields change only in a cycle that handled a command (applyCommand sets
    // result_slot with them): copied then, not every cycle.
    if (report_.result_slot >= 0) {
        s->last_cmd = report_.last_cmd;
        s->last_rejected_cmd = report_.last_rejected_cmd;
        s->reject_code = report_.reject_code;
        s->rejected_count = report_.rejected_count;
        s->cmd_done = report_.cmd_done;
        s->cmd_rejected = report_.cmd_rejected;
        if (report_.reason_changed) {
            std::memcpy(s->reject_reason, report_.reject_reason, sizeof s->reject_reason);
            report_.reason_changed = false;
        }
        s->cmd_results[report_.result_slot] = report_.result;
        if (report_.result & 1u)
            std::memcpy(s->cmd_reasons[report_.result_slot], report_.reject_reason,
                        sizeof s->cmd_reasons[0]);
        report_.result_slot = -1;
    }
    s->cycles = cycles;
    s->missed = missed_;
    if (cycles == 1)
        s->t_start_ns = deadline_ns;
    // Simulated time: the loop's clock runs ahead of the real one, and the watchdog and every
    // reader compare the heartbeat with real time (backend_virtual.c stamps it again before it
    // naps; this keeps the window between publish and nap real too).
    s->heartbeat_ns = virtual_ ? xrf_virtual_real_ns() : wake_ns;
    s->idle_ns = idle_total_;
    if (!posix_) // posix: no out-of-band stage to be demoted from, always 0
        s->demotions = backend_->demotions();
    if (backend_->doorbell_dropped)
        s->doorbell_dropped = backend_->doorbell_dropped();
    s->log_written = shm_->log_ring.head;
    s->log_lost = shm_->log_ring.dropped;
    s->telem_published = shm_->telem_ring.head;
    s->host_lost = host_lost_count_;
    s->monitor_dropped = monitor_truncated_;
    xrf_hist_add_inline(&s->hist[XRF_STAGE_WAKEUP], (uint64_t)(jitter > 0 ? jitter : 0));
    xrf_hist_add_inline(&s->hist[XRF_STAGE_CYCLE], (uint64_t)(end_ns - wake_ns));
    // The stages step() timed this cycle; unrolled, so each histogram's address is a constant.
    // step() times all six every cycle: then one compare instead of six tests.
    constexpr uint32_t kAll = ((1u << (XRF_STAGE_LOGGER + 1)) - 1) & ~((1u << XRF_STAGE_FPGA) - 1);
    const uint32_t mask = report_.stage_mask;
    if (mask == kAll) {
#pragma GCC unroll 8
        for (int i = XRF_STAGE_FPGA; i <= XRF_STAGE_LOGGER; i++) {
            const int64_t d = report_.stage_ns[i];
            xrf_hist_add_inline(&s->hist[i], (uint64_t)(d > 0 ? d : 0));
        }
    } else if (mask != 0) {
        for (int i = XRF_STAGE_FPGA; i <= XRF_STAGE_LOGGER; i++) {
            if (mask & (1u << i)) {
                const int64_t d = report_.stage_ns[i];
                xrf_hist_add_inline(&s->hist[i], (uint64_t)(d > 0 ? d : 0));
            }
        }
    }
    report_.stage_mask = 0;
    xrf_status_write_end_inline(s);

    // Up to 1 kHz the period is 1: no division then (a 64-bit divide is tens of CPU cycles).
    if (pending_doorbell_ && (doorbell_period_ == 1 || cycles % doorbell_period_ == 0)) {
        pending_doorbell_ = false;
        if (xrf_doorbell_should_ring(shm_))
            backend_->ring_doorbell(shm_);
    }
}

// One timing record into its ring (stages not run this cycle: -1). A full ring drops the
// record, counted in timing_ring.dropped and visible as a gap in seq; the loop never waits.
void Runtime::recordTiming(int64_t jitter_ns, int64_t cycle_ns, uint64_t skipped)
{
    const uint64_t seq = timing_seq_++;
    auto *t =
        static_cast<xrf_timing_record *>(xrf_spsc_begin_inline(&shm_->timing_ring, shm_->timing));
    if (t == nullptr)
        return;
    auto stage = [this](int i) { return report_.staged(i) ? report_.stage_ns[i] : (int64_t)-1; };
    t->hdr.seq = seq;
    t->hdr.cycle = cycles_ - 1; // the cycle index the logger stamped during this cycle
    t->hdr.t_ns = cycle_start_ns_;
    t->wakeup_ns = jitter_ns;
    t->fpga_ns = stage(XRF_STAGE_FPGA);
    t->data_ns = stage(XRF_STAGE_DATA);
    t->cmd_ns = stage(XRF_STAGE_CMD);
    t->monitor_ns = stage(XRF_STAGE_MONITOR);
    t->hook_ns = stage(XRF_STAGE_HOOK);
    t->logger_ns = stage(XRF_STAGE_LOGGER);
    t->cycle_ns = cycle_ns;
    t->missed = skipped < (uint64_t)INT32_MAX ? (int32_t)skipped : INT32_MAX;
    xrf_spsc_commit_inline(&shm_->timing_ring, t);
}

void Runtime::monitorWrite(const char *fmt, va_list ap)
{
    if (!onLoopThread()) {
        // Before the loop, or from another thread: the monitor ring has one producer, the loop.
        std::vfprintf(stdout, fmt, ap);
        return;
    }
    auto *line =
        static_cast<xrf_monitor_line *>(xrf_bcast_begin_inline(&shm_->monitor_ring, shm_->monitor));
    int n = std::vsnprintf(line->text, sizeof line->text, fmt, ap);
    if (n < 0)
        n = 0;
    if ((size_t)n >= sizeof line->text) {
        n = (int)sizeof line->text - 1;
        monitor_truncated_++; // published with the status: a loss the host can show
    }
    line->len = (uint32_t)n;
    line->hdr.cycle = cycles_;
    line->hdr.t_ns = now();
    xrf_bcast_commit_inline(&shm_->monitor_ring, line);
    pending_doorbell_ = true;
}

void Runtime::startHelper()
{
    helper_run_.store(true);
    monitor_cursor_ = 0;
    // Keep the helper (disk writes, stdout) off the loop's CPU: the loop's CPU is XRF_CPU, or
    // the one CPU an XRF2 main pinned the thread to.
    int loop_cpu = options_.cpu;
    cpu_set_t current;
    CPU_ZERO(&current);
    if (loop_cpu < 0 && pthread_getaffinity_np(pthread_self(), sizeof current, &current) == 0 &&
        CPU_COUNT(&current) == 1) {
        for (int c = 0; c < CPU_SETSIZE; c++)
            if (CPU_ISSET(c, &current))
                loop_cpu = c;
    }
    pthread_attr_t attr;
    pthread_attr_init(&attr);
    if (loop_cpu >= 0) {
        // The CPUs this process may use (a cpuset may give the run only the loop's): asking for
        // one outside them would make pthread_create fail. The main thread's (the process's
        // pid), not this thread's: the loop thread may be pinned already.
        cpu_set_t allowed;
        CPU_ZERO(&allowed);
        const bool known = sched_getaffinity(getpid(), sizeof allowed, &allowed) == 0;
        cpu_set_t others;
        CPU_ZERO(&others);
        const long n = sysconf(_SC_NPROCESSORS_ONLN);
        for (int c = 0; c < n && c < CPU_SETSIZE; c++)
            if (c != loop_cpu && (!known || CPU_ISSET(c, &allowed)))
                CPU_SET(c, &others);
        if (CPU_COUNT(&others) > 0)
            pthread_attr_setaffinity_np(&attr, sizeof others, &others);
    }
    // In-band work: never the loop's real-time priority, whatever the creating thread has.
    pthread_attr_setinheritsched(&attr, PTHREAD_EXPLICIT_SCHED);
    pthread_attr_setschedpolicy(&attr, SCHED_OTHER);
    sched_param sp{};
    pthread_attr_setschedparam(&attr, &sp);
    if (pthread_create(&helper_, &attr, &Runtime::helperMain, this) == 0)
        helper_started_ = true;
    else
        std::fprintf(stderr, "xrf: warning: no helper thread: monitor and log file disabled\n");
    pthread_attr_destroy(&attr);
}

void *Runtime::helperMain(void *self)
{
    auto *rt = static_cast<Runtime *>(self);
    // The process's SIGINT/SIGTERM land here (the loop thread blocks them, see enter()).
    sigset_t stop_signals;
    sigemptyset(&stop_signals);
    sigaddset(&stop_signals, SIGINT);
    sigaddset(&stop_signals, SIGTERM);
    pthread_sigmask(SIG_UNBLOCK, &stop_signals, nullptr);
    // The helper is in-band housekeeping; a 10 ms poll keeps it off the loop's doorbell, whose
    // wake-ups are for hosts.
    while (rt->helper_run_.load()) {
        rt->helperDrain(false);
        struct timespec ts = {0, 10 * 1000 * 1000};
        nanosleep(&ts, nullptr);
    }
    rt->helperDrain(true);
    return nullptr;
}

void Runtime::helperDrain(bool final)
{
    xrf_monitor_line line;
    uint64_t lost = 0;
    // The geometry xrf_shm_init gave the ring, from this side's own memory (channels.h: a
    // reader never takes it from the segment, the loop's own helper included).
    static const xrf_ring_geom geom = {XRF_MONITOR_SLOTS, sizeof(xrf_monitor_line)};
    while (xrf_bcast_read_g(&shm_->monitor_ring, &geom, shm_->monitor, &monitor_cursor_, &line,
                            &lost) == 1) {
        if (!options_.quiet) {
            const uint32_t len = line.len < XRF_MONITOR_TEXT ? line.len : XRF_MONITOR_TEXT;
            std::fwrite(line.text, 1, len, stdout);
            if (len == 0 || line.text[len - 1] != '\n')
                std::fputc('\n', stdout);
        }
    }
    if (lost && !options_.quiet)
        std::fprintf(stdout, "xrf: %llu monitor lines were overwritten before printing\n",
                     (unsigned long long)lost);
    std::fflush(stdout);
    if (shm_->log_meta.writer == XRF_LOG_WRITER_PROCESS)
        logfile_drain(shm_, &shm_->log_meta, &shm_->log_ring, shm_->log_data, XRF_LOG_RING_BYTES,
                      &log_sink_, program_, final);
    if (timing_on_ && shm_->timing_meta.writer == XRF_LOG_WRITER_PROCESS)
        logfile_drain(shm_, &shm_->timing_meta, &shm_->timing_ring, shm_->timing,
                      sizeof shm_->timing, &timing_sink_, program_, final);
}

void Runtime::leave()
{
    if (shm_ == nullptr)
        return;
    // Why loop() returned, for the host's record of the run: a process that exits without
    // passing here (exit() in a hook, a crash) leaves XRF_END_NONE behind.
    int32_t why = XRF_END_RETURNED;
    if (g_signal_stop)
        why = XRF_END_SIGNAL;
    else if (report_.state == XRF_STATE_QUIT)
        why = XRF_END_QUIT;
    else if (options_.max_cycles && cycles_ >= options_.max_cycles)
        why = XRF_END_CYCLE_LIMIT;
    xrf_status_write_begin_inline(&shm_->status);
    shm_->status.running = 0;
    shm_->status.end_reason = why;
    xrf_status_write_end_inline(&shm_->status);
    if (backend_ != nullptr)
        backend_->thread_teardown();
    if (helper_started_) {
        helper_run_.store(false);
        pthread_join(helper_, nullptr);
        helper_started_ = false;
    }
    // The helper is gone: this thread takes the stop signals again (a pending one runs now).
    if (signals_blocked_) {
        pthread_sigmask(SIG_SETMASK, &saved_sigmask_, nullptr);
        signals_blocked_ = false;
    }
    if (xrf_doorbell_should_ring(shm_))
        xrf_doorbell_wake(shm_);
    logfile_close(&log_sink_);
    logfile_close(&timing_sink_);
    if (dma_latency_fd_ >= 0) {
        close(dma_latency_fd_);
        dma_latency_fd_ = -1;
    }
}

} // namespace xrf

// --- the few EVL calls XRF2 student code makes, for builds without libevl -----------------------
#ifndef XRF_HAVE_EVL
extern "C" int evl_init(void)
{
    // libevl's evl_init also locks memory; keep that meaning.
    if (mlockall(MCL_CURRENT | MCL_FUTURE) != 0)
        std::fprintf(stderr, "xrf: warning: mlockall failed (%s)\n", std::strerror(errno));
    return 0;
}

extern "C" int evl_printf(const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    xrf::Runtime::instance().monitorWrite(fmt, ap);
    va_end(ap);
    return 0;
}
#endif
