// xrf/runtime.hpp — the per-process runtime behind the XRF2 classes: options from the
// environment, the run's shared memory, the backend, the ico transport, the in-band helper
// thread (monitor printing, log file writing) and the per-cycle status publication.
//
// Everything that may allocate, print or make a system call happens in enter() and leave(), or
// on the helper thread. The per-cycle functions touch only memory that exists since enter().
#pragma once

#include <atomic>
#include <cstdarg>
#include <cstdint>
#include <ctime>
#include <pthread.h>
#include <signal.h>

#include "xrf/backend.h"
#include "xrf/channels.h"
#include "xrf/cycle_counter.h"
#include "xrf/ico.h"
#include "xrf/logformat.h"

namespace xrf
{

// The in-band file writer's state for one log channel (the logger's, the timing records).
struct LogSink {
    int fd = -1;
    uint64_t generation = 0;
    bool reported = false;  // a write failure was reported once
    bool layout_ok = false; // meta, geom and tail below hold a checked layout
    xrf_log_meta meta{};    // the channel's layout as checked when its generation changed
    xrf_ring_geom geom{};   // its ring's geometry, in this writer's memory (xrf_log_meta_check)
    uint64_t tail = 0;      // the consumer's position, kept here and published to the ring
    char header[XRF_LOGFILE_HEADER_MAX]; // a segment header is formatted here (no allocation)
};

// Priority the loop thread gets when neither XRF_PRIO nor the student's main chose one.
constexpr int kDefaultPriority = 80;

struct Options {
    char shm_name[XRF_NAME_MAX] = "xrf";
    // XRF_SHM_FD: the segment, made by whoever started the loop (the appliance: a memfd whose
    // size is sealed, so the loop cannot shrink it under the host's mapping). -1: create
    // /dev/shm/<shm_name> as a plain `xrf run` does.
    int shm_fd = -1;
    char backend[16] = "auto";
    char transport[16] = "auto";
    char sim[16] = "relbot";
    char sim_faults[256] = "";
    char spi_device[128] = "/dev/spidev0.0";
    uint32_t spi_speed = 31000000;
    unsigned freq_override = 0;
    int cpu = -1;
    int priority =
        -1; // -1: SCHED_FIFO kDefaultPriority unless main already made the thread real-time
    double pwm_limit = XRF_ICO_DEFAULT_PWM_LIMIT;
    char log_dir[XRF_PATH_MAX] = "";
    int log_writer = XRF_LOG_WRITER_PROCESS;
    uint32_t host_timeout_ms = 0;
    uint32_t host_timeout_action = XRF_HOST_LOST_ACTION_STOP;
    uint64_t max_cycles = 0;
    bool quiet = false;
    bool log_timing = false; // XRF_LOG_TIMING=1: every cycle's stage timing into cycle_timing.xrf
    // XRF_VIRTUAL_TIME: 0 real time; 1 simulated time, free-running; 2 ("hold") simulated time,
    // held after the first cycle until the host raises xrf_vtime.run_until.
    int virtual_time = 0;

    // Reads XRF_* (docs/developers/architecture.md). Returns 0 or -EINVAL after printing why.
    int fromEnvironment();
};

// What one cycle reports; published to xrf_status under the seqlock at the end of the cycle.
struct CycleReport {
    int32_t state = XRF_STATE_IDLE;
    int32_t last_error = 0;
    int32_t last_cmd = 0;
    int32_t last_rejected_cmd = 0;
    int32_t reject_code = XRF_REJECT_NONE;
    uint32_t rejected_count = 0;
    uint64_t cmd_done = 0;
    uint64_t cmd_rejected = 0;
    bool reason_changed = false;
    int result_slot = -1; // the cmd_results slot written this cycle, -1 if none
    uint64_t result = 0;
    char reject_reason[XRF_REASON_MAX] = "";
    int64_t stage_ns[XRF_STAGE_COUNT] = {};
    uint32_t stage_mask = 0; // bit i: stage_ns[i] was set this cycle
    bool staged(int i) const { return (stage_mask >> i) & 1u; }
};

class Runtime
{
public:
    // Inline: the loop asks for it several times a cycle. self_ is constant-initialised (null
    // before any constructor runs), so a static constructor that asks first still gets it made.
    static Runtime &instance() { return self_ != nullptr ? *self_ : create(); }

    // --- before the loop (constructors, in-band) ---
    const Options &options();
    // Message layout of a XenoFrtRosIco, recorded for the info block.
    void describe(unsigned write_decimator_freq, unsigned monitor_freq, const char *ros2xeno_schema,
                  uint32_t ros2xeno_size, const char *xeno2ros_schema, uint32_t xeno2ros_size);
    unsigned effectiveFrequency(unsigned requested);
    // The ico-board transport chosen by XRF_TRANSPORT; opened on first use. NULL on failure
    // (reason printed once).
    xrf_ico_transport *transport();
    // XRF_PWM_LIMIT as a PWM magnitude; computed once (the options do not change in a run).
    int16_t pwmMax()
    {
        if (pwm_max_ < 0)
            pwm_max_ = xrf_ico_pwm_max(options().pwm_limit);
        return pwm_max_;
    }
    void setProgramName(const char *name);

    // --- loop lifecycle (loop thread) ---
    int enter(unsigned cycle_freq); // 0, or -errno after printing why
    void leave();
    bool active() const { return shm_ != nullptr; }

    // --- per cycle (loop thread, real-time) ---
    // The posix backend's clock read inline (what its now_ns does): six of them a cycle.
    int64_t now() const
    {
        if (posix_) {
            struct timespec ts;
            clock_gettime(CLOCK_MONOTONIC, &ts); /* vDSO: no system call */
            return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
        }
        return backend_->now_ns();
    }
    int sleepUntil(int64_t t) const { return backend_->sleep_until(t); }
    bool virtualTime() const { return virtual_; }
    xrf_shm *shm() { return shm_; }
    uint64_t cycle() const { return cycles_; }
    void beginCycle(int64_t wake_ns)
    {
        cycle_start_ns_ = wake_ns;
        if (counter_mult_ != 0)
            counter_start_ = xrf_cycle_counter();
    }
    int64_t cycleStart() const { return cycle_start_ns_; }
    // Nanoseconds since beginCycle(): a stage boundary inside the cycle. From the CPU's counter
    // when enter() found a usable one (xrf/cycle_counter.h), else from now(). Durations only:
    // wake-up, end, deadlines and every timestamp a host sees come from now().
    int64_t sinceCycleStart() const
    {
        return counter_mult_ != 0 ? sinceCycleStart<true>() : sinceCycleStart<false>();
    }
    // The same with the choice made by the caller (stageCounterMult() != 0), once per cycle.
    template <bool kCounter> int64_t sinceCycleStart() const
    {
        if (kCounter)
            return xrf_cycle_counter_ns(xrf_cycle_counter() - counter_start_, counter_mult_);
        return now() - cycle_start_ns_;
    }
    // Whether stage times come from the CPU's counter (0: from the clock); ns per tick, 32.32.
    uint64_t stageCounterMult() const { return counter_mult_; }
    uint64_t missed() const { return missed_; } // periods in which no cycle started
    uint64_t idleNs() const { return idle_total_; }
    bool onLoopThread() const
    {
        return shm_ != nullptr && pthread_equal(pthread_self(), loop_thread_);
    }
    CycleReport &report() { return report_; }
    void stage(int idx, int64_t ns)
    {
        report_.stage_ns[idx] = ns;
        report_.stage_mask |= 1u << idx;
    }
    // step()'s form: the durations stored one by one, the mask of all of them set once.
    void stageNs(int idx, int64_t ns) { report_.stage_ns[idx] = ns; }
    void markStaged(uint32_t mask) { report_.stage_mask |= mask; }
    void notifyHost() { pending_doorbell_ = true; }
    // A cycle boundary, before the controller computes: takes the host's pending parameter set,
    // if any (xrf/params.h). Idle, this is one acquire load and a compare.
    void takeParams()
    {
        if (__atomic_load_n(&shm_->params.req_seq, __ATOMIC_ACQUIRE) != params_seen_)
            applyParams();
    }
    // Publishes status and histograms for the cycle that just ended; rings the doorbell.
    // skipped: the periods the loop passes over after this cycle (it woke or ended after the
    // next one began), added to the missed count; 0 for a cycle on time.
    void endCycle(int64_t wake_ns, int64_t deadline_ns, int64_t end_ns, uint64_t skipped,
                  int64_t idle_ns);
    // Set by SIGINT/SIGTERM, XRF_MAX_CYCLES, or the host.
    bool stopRequested() const;
    void requestStop() { stop_.store(true, std::memory_order_relaxed); }
    // The host's heartbeat went stale this cycle (edge-triggered); 0 or an XRF_HOST_LOST_ACTION_*.
    // Inline: every cycle asks, and the answer is almost always "nothing changed".
    uint32_t checkHostHeartbeat(int64_t now_ns)
    {
        const uint32_t timeout_ms = __atomic_load_n(&shm_->host_timeout_ms, __ATOMIC_RELAXED);
        if (timeout_ms == 0)
            return XRF_HOST_LOST_ACTION_IGNORE;
        const int64_t hb = __atomic_load_n(&shm_->host_heartbeat_ns, __ATOMIC_RELAXED);
        if (virtual_)
            now_ns =
                xrf_virtual_real_ns(); // the host beats in real time; the loop's clock runs ahead
        // No heartbeat yet: the host has not attached; supervision starts with the first one.
        const bool stale = hb != 0 && now_ns - hb > (int64_t)timeout_ms * 1000000LL;
        return stale == host_lost_ ? (uint32_t)XRF_HOST_LOST_ACTION_IGNORE : hostLostEdge(stale);
    }

    // Monitor text (rate limiting is XenoFrtMonitor's job): never blocks, drops when the host is
    // far behind (counted).
    void monitorWrite(const char *fmt, va_list ap);

private:
    Runtime() = default;
    static Runtime &create();
    static Runtime *self_;
    int createShm();
    int mapShm(int fd, const char *what, bool keep_fd); // maps, zeroes, xrf_shm_init
    int setChannels(); // the bench's channel count into the segment (after the board opens)
    void startHelper();
    static void *helperMain(void *self);
    void helperDrain(bool final);
    void recordTiming(int64_t jitter_ns, int64_t cycle_ns, uint64_t skipped);
    void applyParams();
    void calibrateStageCounter(uint64_t c0, int64_t t0);
    uint32_t hostLostEdge(bool stale); // the heartbeat's state changed: count, say what to do

    Options options_;
    bool options_loaded_ = false;
    xrf_shm *shm_ = nullptr;
    size_t shm_size_ = 0;
    uint32_t host_channels_ = 0; // the channel count the host wrote into its segment, 0: none
    const xrf_backend *backend_ = nullptr;
    xrf_ico_transport *transport_ = nullptr;
    bool transport_failed_ = false;
    char transport_name_[16] = "";
    char program_[XRF_NAME_MAX] = "";

    unsigned write_decimator_freq_ = 0, monitor_freq_ = 0;
    const char *ros2xeno_schema_ = "";
    const char *xeno2ros_schema_ = "";
    uint32_t ros2xeno_size_ = 0, xeno2ros_size_ = 0;

    CycleReport report_;
    uint64_t cycles_ = 0, missed_ = 0, idle_total_ = 0;
    uint32_t doorbell_period_ = 1;
    int16_t pwm_max_ = -1;     // pwmMax() once computed
    bool posix_ = false;       // backend_ is the posix one: its clock is read inline, no demotions
    uint32_t params_seen_ = 0; // req_seq of the last parameter set taken (xrf/params.h)
    bool pending_doorbell_ = false;
    bool host_lost_ = false;
    uint64_t host_lost_count_ = 0;
    uint64_t monitor_truncated_ = 0;
    int rt_sched_ = 0;
    int64_t cycle_start_ns_ = 0;
    uint64_t counter_start_ = 0; // the CPU's counter at beginCycle()
    uint64_t counter_mult_ = 0;  // its ns per tick in 32.32 fixed point; 0: not used
    pthread_t loop_thread_{};

    std::atomic<bool> stop_{false};
    std::atomic<bool> helper_run_{false};
    pthread_t helper_{};
    bool helper_started_ = false;
    bool signals_blocked_ = false; // SIGINT/SIGTERM blocked on the loop thread (enter())
    sigset_t saved_sigmask_{};
    uint64_t monitor_cursor_ = 0;
    LogSink log_sink_;
    LogSink timing_sink_;
    int dma_latency_fd_ = -1;
    bool timing_on_ = false;
    uint64_t timing_seq_ = 0; // counts dropped records too: gaps stay visible in the file
    bool virtual_ = false;    // simulated time (backend_virtual.c): the loop's clock is not real
};

} // namespace xrf
