// XenoFrtRosIcoCore: one cycle in XRF2's order — FPGA exchange, data channel, command channel,
// monitor, state hook, logger — each stage timed into the shared histograms.
#include "XenoFrtRosIcoCore.hpp"

#include <cerrno>
#include <cstring>
#include <type_traits>

#include "xrf/ico.h"
#include "xrf/runtime.hpp"
#include "xrf2_compat.hpp"
#include "channels_inline.h" // the per-cycle handoffs, inlined (issue 30 item 5)

namespace
{

bool outputsAllowed(int state)
{
    // No motion before an explicit initialise, nor in ERROR or after QUIT.
    return state != IDLE_STATE && state != ERROR_STATE && state != QUIT_STATE;
}

} // namespace

XenoFrtRosIcoCore::XenoFrtRosIcoCore(unsigned cycle_freq, unsigned write_decimator_freq,
                                     unsigned monitor_freq, XenoFileHandler &file, void *log_data)
    : XenoFrtLoop(cycle_freq),
      monitor(xrf::Runtime::instance().effectiveFrequency(cycle_freq), monitor_freq),
      logger(file, log_data),
      state_machine([this] { return initialising(); }, [this] { return initialised(); },
                    [this] { return run(); }, [this] { return stopping(); },
                    [this] { return stopped(); }, [this] { return pausing(); },
                    [this] { return paused(); }, [this] { return error(); })
{
    monitor_freq_ = monitor_freq;
    this->monitor_freq = (int)monitor_freq;
    const unsigned f = xrf::Runtime::instance().effectiveFrequency(cycle_freq);
    // 0 disables publishing (XRF2 divided by zero here).
    decimator_ =
        write_decimator_freq == 0 ? 0 : (f + write_decimator_freq / 2) / write_decimator_freq;
    if (write_decimator_freq != 0 && decimator_ == 0)
        decimator_ = 1;
    decimator_count_ = decimator_ ? decimator_ - 1 : 0; // the first cycle publishes
}

void XenoFrtRosIcoCore::xrfMessages(void *ros_msg, uint32_t ros_size, const char *ros_schema,
                                    const void *xeno_msg, uint32_t xeno_size,
                                    const char *xeno_schema)
{
    ros_msg_ = ros_msg;
    ros_size_ = ros_size;
    xeno_msg_ = xeno_msg;
    xeno_size_ = xeno_size;
    const unsigned f = xrf::Runtime::instance().effectiveFrequency(getCycleFrequency());
    xrf::Runtime::instance().describe(decimator_ ? (f + decimator_ / 2) / decimator_ : 0,
                                      monitor_freq_, ros_schema, ros_size, xeno_schema, xeno_size);
}

void XenoFrtRosIcoCore::publishTelemetry(xrf::Runtime &rt, int state)
{
    xrf_shm *shm = rt.shm();
    auto *t = static_cast<xrf_telemetry *>(xrf_bcast_begin_inline(&shm->telem_ring, shm->telem));
    t->hdr.cycle = rt.cycle();
    t->hdr.t_ns = rt.cycleStart();
    t->state = state;
    t->enc[0] = sample_data.channel1;
    t->enc[1] = sample_data.channel2;
    t->enc[2] = sample_data.channel3;
    t->enc[3] = sample_data.channel4;
    t->din[0] = sample_data.channel1_1;
    t->din[1] = sample_data.channel1_2;
    t->din[2] = sample_data.channel2_1;
    t->din[3] = sample_data.channel2_2;
    t->din[4] = sample_data.channel3_1;
    t->din[5] = sample_data.channel3_2;
    t->din[6] = sample_data.channel4_1;
    t->din[7] = sample_data.channel4_2;
    // Board 0's four channels, then the bench's other boards'. A board the bench lacks is never
    // written: its fields stay as the host created the ring, zero (the count is fixed for the run).
    std::memcpy(t->pwm, ico_io.lastPwm(), XRF_ICO_CHANNELS * sizeof t->pwm[0]);
    std::memcpy(t->dout, ico_io.lastDout(), XRF_ICO_CHANNELS * sizeof t->dout[0]);
    for (int b = 1; b <= extra_boards_; b++) {
        const int c = b * XRF_ICO_CHANNELS;
        const IcoIo::IcoRead &in = sample_more[b - 1];
        t->enc[c] = in.channel1;
        t->enc[c + 1] = in.channel2;
        t->enc[c + 2] = in.channel3;
        t->enc[c + 3] = in.channel4;
        std::memcpy(&t->din[2 * c], &in.channel1_1, 2 * XRF_ICO_CHANNELS);
        std::memcpy(&t->pwm[c], ico_more[b - 1].lastPwm(), XRF_ICO_CHANNELS * sizeof t->pwm[0]);
        std::memcpy(&t->dout[c], ico_more[b - 1].lastDout(), XRF_ICO_CHANNELS);
    }
    t->size = xeno_size_;
    t->ros2xeno_t_sent_ns = ros_t_sent_;
    std::memcpy(t->data, xeno_msg_, xeno_size_);
    xrf_bcast_commit_inline(&shm->telem_ring, t);
    rt.notifyHost();
}

// A command taken from the ring, judged by the state machine. Out of line: a cycle with a command
// is rare, and without this the poll of every cycle paid this function's register saves.
__attribute__((noinline)) static void judgeCommand(FullStateMachine &sm, xrf::Runtime &rt,
                                                   const xrf_cmd_slot &c)
{
    xrf::CycleReport &rep = rt.report();
    const int before = sm.getState();
    const bool accepted = sm.command(c.cmd) == 0;
    rep.result_slot = (int)(c.ticket % XRF_CMD_RESULTS);
    rep.result = (c.ticket << 1) | (accepted ? 0u : 1u);
    if (accepted) {
        rep.last_cmd = c.cmd;
    } else {
        rep.last_rejected_cmd = c.cmd;
        rep.reject_code = -xrf_cmd_transition(before, c.cmd);
        rep.rejected_count++;
        rep.cmd_rejected = c.ticket;
        xrf_cmd_reject_reason(before, c.cmd, rep.reject_reason, sizeof rep.reject_reason);
        rep.reason_changed = true;
    }
    rep.cmd_done = c.ticket;
    rt.notifyHost();
}

// inline: called only by step(), below (its definition is this file's alone).
inline void XenoFrtRosIcoCore::applyCommand(xrf::Runtime &rt)
{
    xrf_cmd_slot c;
    // One command per cycle: the hook of the new state runs before the next command is judged,
    // so "initialise, start" sent back to back works as a student expects.
    if (xrf_cmd_poll_inline(&rt.shm()->cmd, &c))
        judgeCommand(state_machine, rt, c);
    switch (rt.checkHostHeartbeat(rt.cycleStart())) {
    case XRF_HOST_LOST_ACTION_PAUSE:
        state_machine.pause();
        break;
    case XRF_HOST_LOST_ACTION_STOP:
        state_machine.stop();
        break;
    default:
        break;
    }
}

int XenoFrtRosIcoCore::step()
{
    xrf::Runtime &rt = xrf::Runtime::instance();
    xrf_shm *shm = rt.shm();
    xrf::CycleReport &rep = rt.report();

    // The cycle, in two copies: whether stage times come from the CPU's counter is fixed for the
    // run (Runtime::enter), so it is decided once here, not at each of the six stage boundaries.
    auto cycle = [&](auto counter) -> int {
        constexpr bool kCounter = decltype(counter)::value;
        // 1. FPGA exchange: last cycle's actuate_data out, this cycle's sample_data in.
        // The stage boundaries e1..e6 (ns since the cycle's start, Runtime::sinceCycleStart)
        // also become XRF2's t2..t7 as offsets from t1 (no extra clock read, no division).
        const int64_t s0 = rt.cycleStart();
        const struct timespec base = xrf2::toTimespec(s0); // kept in registers across the calls
        t1 = base;
        const bool allowed = outputsAllowed(state_machine.getState());
        // The other boards first, board 0 last: the simulated board steps its plant on board
        // 0's exchange, so every board's outputs of this cycle take effect in the same step.
        if (extra_boards_ != 0 && extraBoards(rt) > 0) {
            for (int b = 0; b < extra_boards_; b++) {
                ico_more[b].setOutputsEnabled(allowed);
                if (ico_more[b].update_io(actuate_more[b], &sample_more[b]) != 0 &&
                    state_machine.getState() != ERROR_STATE)
                    state_machine.fail(-EIO);
            }
        }
        ico_io.setOutputsEnabled(allowed);
        if (ico_io.update_io(actuate_data, &sample_data) != 0 &&
            state_machine.getState() != ERROR_STATE)
            state_machine.fail(-EIO);
        const int64_t e1 = rt.sinceCycleStart<kCounter>();
        rt.stageNs(XRF_STAGE_FPGA, e1);
        t2 = xrf2::toTimespecAfter(base, s0, e1);

        // 2. Data channel: the newest Ros2Xeno (a torn or absent one keeps the last), Xeno2Ros out.
        xrf_data_in_try_read(&shm->ros2xeno, &ros_seq_, ros_msg_, ros_size_, &ros_t_sent_);
        if (decimator_ && ++decimator_count_ >= decimator_) {
            decimator_count_ = 0;
            publishTelemetry(rt, state_machine.getState());
        }
        const int64_t e2 = rt.sinceCycleStart<kCounter>();
        rt.stageNs(XRF_STAGE_DATA, e2 - e1);
        t3 = xrf2::toTimespecAfter(base, s0, e2);

        // 3. Command channel.
        applyCommand(rt);
        rep.state = state_machine.getState();
        const int64_t e3 = rt.sinceCycleStart<kCounter>();
        rt.stageNs(XRF_STAGE_CMD, e3 - e2);
        t4 = xrf2::toTimespecAfter(base, s0, e3);

        // 4. Monitor.
        monitor.update();
        const int64_t e4 = rt.sinceCycleStart<kCounter>();
        rt.stageNs(XRF_STAGE_MONITOR, e4 - e3);
        t5 = xrf2::toTimespecAfter(base, s0, e4);

        // 5. The current state's hook.
        const int quit = state_machine.step();
        if (ico_io.boardMissing() && state_machine.getState() != ERROR_STATE)
            state_machine.fail(-ENODEV);
        const int64_t e5 = rt.sinceCycleStart<kCounter>();
        rt.stageNs(XRF_STAGE_HOOK, e5 - e4);
        t6 = xrf2::toTimespecAfter(base, s0, e5);

        // 6. Logger.
        logger.log();
        const int64_t e6 = rt.sinceCycleStart<kCounter>();
        rt.stageNs(XRF_STAGE_LOGGER, e6 - e5);
        t7 = xrf2::toTimespecAfter(base, s0, e6);
        return quit;
    };
    const int quit =
        rt.stageCounterMult() != 0 ? cycle(std::true_type{}) : cycle(std::false_type{});
    rt.markStaged(1u << XRF_STAGE_FPGA | 1u << XRF_STAGE_DATA | 1u << XRF_STAGE_CMD |
                  1u << XRF_STAGE_MONITOR | 1u << XRF_STAGE_HOOK | 1u << XRF_STAGE_LOGGER);

    rep.state = state_machine.getState();
    rep.last_error = state_machine.getError();
    if (rep.state != published_state_) {
        published_state_ = rep.state;
        rt.notifyHost();
    }
    return quit;
}

int XenoFrtRosIcoCore::extraBoards(xrf::Runtime &rt)
{
    if (extra_boards_ < 0) {
        const xrf_ico_transport *t = rt.transport();
        const int boards = t == nullptr || t->xfer_board == nullptr ? 1 : t->boards;
        extra_boards_ = boards <= 1 ? 0 : (boards > XRF_MAX_BOARDS ? XRF_MAX_BOARDS : boards) - 1;
    }
    return extra_boards_;
}

void XenoFrtRosIcoCore::xrfAfterLastCycle()
{
    // Whatever ended the loop (QUIT, a signal, XRF_MAX_CYCLES), the motors end at PWM 0.
    IcoIo::IcoWrite zero{};
    for (int b = 0; b < extra_boards_; b++) {
        ico_more[b].setOutputsEnabled(false);
        ico_more[b].update_io(zero, &sample_more[b]);
    }
    ico_io.setOutputsEnabled(false);
    ico_io.update_io(zero, &sample_data);
}
