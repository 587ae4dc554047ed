#include "ControlLoop.hpp"

#include <cmath>

namespace {
constexpr int encoder_range = 16384;                // 14-bit counters
constexpr double counts_per_rad = 4096.0 / (2.0 * M_PI);  // 1024 lines x 4, at the motor shaft
constexpr double pwm_full_scale = 2047.0;           // the framework clamps to its limit (20 %)
}

ControlLoop::ControlLoop(unsigned write_decimator_freq, unsigned monitor_freq)
    : XenoFrt20Sim(write_decimator_freq, monitor_freq, file, &log_data),
      file(true, "logs/controlloop", "bin")
{
    logger.addVariable("setpoint_1", double_);
    logger.addVariable("position_1", double_);
    logger.addVariable("setpoint_2", double_);
    logger.addVariable("position_2", double_);
    logger.addVariable("steer_1", double_);
    logger.addVariable("steer_2", double_);
}

int ControlLoop::unwrap(int raw, int &last, long &offset) const
{
    int diff = raw - last;
    if (diff > encoder_range / 2)
        offset -= encoder_range;
    else if (diff < -encoder_range / 2)
        offset += encoder_range;
    last = raw;
    return static_cast<int>(raw + offset);
}

int ControlLoop::initialising()
{
    actuate_data = {};
    if (!board_initialised) {
        // The FPGA exchange of this cycle ran before the board was initialised; take the
        // encoder zero from the next cycle's sample.
        ico_io.init();
        logger.initialise();
        board_initialised = true;
        return 0;
    }
    board_initialised = false;  // so that a reset initialises the board again

    // The positions count from where the motors are now.
    last_raw_1 = sample_data.channel1;
    last_raw_2 = sample_data.channel2;
    offset_1 = -last_raw_1;
    offset_2 = -last_raw_2;

    u[0] = u[1] = u[2] = u[3] = 0.0;
    controller.Initialize(u, y, 0.0);
    // 20-sim bakes the experiment's finish time into the code; on the bench the controller
    // must keep running, so switch it off (0 = no finish time).
    controller.SetFinishTime(0.0);
    return 1;
}

int ControlLoop::initialised()
{
    actuate_data = {};
    return 0;
}

int ControlLoop::run()
{
    logger.start();

    u[0] = ros_msg.steer_left;
    u[1] = unwrap(sample_data.channel1, last_raw_1, offset_1) / counts_per_rad;
    u[2] = ros_msg.steer_right;
    u[3] = unwrap(sample_data.channel2, last_raw_2, offset_2) / counts_per_rad;

    controller.Calculate(u, y);

    actuate_data.pwm1 = static_cast<int16_t>(std::lround(y[0] * pwm_full_scale));
    actuate_data.pwm2 = static_cast<int16_t>(std::lround(y[1] * pwm_full_scale));

    xeno_msg.pos_left = u[1];
    xeno_msg.pos_right = u[3];

    log_data = {u[0], u[1], u[2], u[3], y[0], y[1]};
    monitor.printf("t %.2f  sp %.3f %.3f  pos %.3f %.3f  steer %.3f %.3f\n", controller.GetTime(),
                   u[0], u[2], u[1], u[3], y[0], y[1]);
    return 0;
}

int ControlLoop::stopping()
{
    actuate_data = {};
    controller.Terminate(u, y);
    logger.stop();
    return 1;
}

int ControlLoop::stopped()
{
    actuate_data = {};
    return 0;
}

int ControlLoop::pausing()
{
    actuate_data = {};
    return 1;
}

int ControlLoop::paused()
{
    actuate_data = {};
    return 0;
}

int ControlLoop::error()
{
    actuate_data = {};
    return 0;
}
