// XenoFrtRosIcoCore: one cycle in XRF2's order — FPGA exchange, data channel, command channel,
// monitor, state hook, logger — each stage timed into the shared histograms.
#include "XenoFrtRosIcoCore.hpp"

#include <cerrno>
#include <cstring>

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
    std::memcpy(t->pwm, ico_io.lastPwm(), sizeof t->pwm);
    std::memcpy(t->dout, ico_io.lastDout(), sizeof t->dout);
    t->size = xeno_size_;
    t->ros2xeno_t_sent_ns = ros_t_sent_;
    std::memcpy(t->data, xeno_msg_, xeno_size_);
    xrf_bcast_commit_inline(&shm->telem_ring, t);
    rt.notifyHost();
}

void XenoFrtRosIcoCore::applyCommand(xrf::Runtime &rt)
{
    xrf_shm *shm = rt.shm();
    xrf::CycleReport &rep = rt.report();
    xrf_cmd_slot c;
    // One command per cycle: the hook of the new state runs before the next command is judged,
    // so "initialise, start" sent back to back works as a student expects.
    if (xrf_cmd_poll_inline(&shm->cmd, &c)) {
        const int before = state_machine.getState();
        const bool accepted = state_machine.command(c.cmd) == 0;
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

    // 1. FPGA exchange: last cycle's actuate_data out, this cycle's sample_data in.
    // The stage boundaries s0..s6 also become XRF2's t1..t7 (converted, no extra clock read).
    const int64_t s0 = rt.cycleStart();
    t1 = xrf2::toTimespec(s0);
    ico_io.setOutputsEnabled(outputsAllowed(state_machine.getState()));
    if (ico_io.update_io(actuate_data, &sample_data) != 0 &&
        state_machine.getState() != ERROR_STATE)
        state_machine.fail(-EIO);
    const int64_t s1 = rt.now();
    rt.stage(XRF_STAGE_FPGA, s1 - s0);
    t2 = xrf2::toTimespecAfter(t1, s0, s1);

    // 2. Data channel: the newest Ros2Xeno (a torn or absent one keeps the last), Xeno2Ros out.
    xrf_data_in_try_read(&shm->ros2xeno, &ros_seq_, ros_msg_, ros_size_, &ros_t_sent_);
    if (decimator_ && ++decimator_count_ >= decimator_) {
        decimator_count_ = 0;
        publishTelemetry(rt, state_machine.getState());
    }
    const int64_t s2 = rt.now();
    rt.stage(XRF_STAGE_DATA, s2 - s1);
    t3 = xrf2::toTimespecAfter(t1, s0, s2);

    // 3. Command channel.
    applyCommand(rt);
    rep.state = state_machine.getState();
    const int64_t s3 = rt.now();
    rt.stage(XRF_STAGE_CMD, s3 - s2);
    t4 = xrf2::toTimespecAfter(t1, s0, s3);

    // 4. Monitor.
    monitor.update();
    const int64_t s4 = rt.now();
    rt.stage(XRF_STAGE_MONITOR, s4 - s3);
    t5 = xrf2::toTimespecAfter(t1, s0, s4);

    // 5. The current state's hook.
    const int quit = state_machine.step();
    if (ico_io.boardMissing() && state_machine.getState() != ERROR_STATE)
        state_machine.fail(-ENODEV);
    const int64_t s5 = rt.now();
    rt.stage(XRF_STAGE_HOOK, s5 - s4);
    t6 = xrf2::toTimespecAfter(t1, s0, s5);

    // 6. Logger.
    logger.log();
    const int64_t s6 = rt.now();
    rt.stage(XRF_STAGE_LOGGER, s6 - s5);
    t7 = xrf2::toTimespecAfter(t1, s0, s6);

    rep.state = state_machine.getState();
    rep.last_error = state_machine.getError();
    if (rep.state != published_state_) {
        published_state_ = rep.state;
        rt.notifyHost();
    }
    return quit;
}

void XenoFrtRosIcoCore::xrfAfterLastCycle()
{
    // Whatever ended the loop (QUIT, a signal, XRF_MAX_CYCLES), the motors end at PWM 0.
    ico_io.setOutputsEnabled(false);
    IcoIo::IcoWrite zero{};
    ico_io.update_io(zero, &sample_data);
}
