#include "StageController.hpp"

#include <cmath>

namespace {
constexpr double counts_per_motor_rev = 4096.0;  // 1024-line encoder, quadrature
constexpr double lead = 0.008;                   // m of carriage travel per screw revolution
constexpr double m_per_count = lead / counts_per_motor_rev;
constexpr double pwm_limit = 409.0;  // the framework's default 20 % limit

// Keep setpoints inside the end stops (+-100 mm from the start) with a margin: driving into a
// stop only heats the motor.
constexpr double position_max = 0.090;

// Gains in PWM counts per m of position error (tuned on the simulated stage). The integral
// term works the carriage through the nut's friction, which a proportional term alone cannot
// within about 2 mm.
constexpr double kp = 40000.0, ki = 80000.0, kd = 800.0;

double clamp(double v, double lim)
{
    return v > lim ? lim : (v < -lim ? -lim : v);
}
}

StageController::StageController(unsigned cycle_freq, unsigned write_decimator_freq,
                                 unsigned monitor_freq)
    : XenoFrtRosIco(cycle_freq, write_decimator_freq, monitor_freq, file, &log_data),
      file(true, "logs/stage", "bin"),
      pid(kp, ki, kd, pwm_limit, 1.0 / cycle_freq)
{
    logger.addVariable("position_setpoint", double_);
    logger.addVariable("position", double_);
    logger.addVariable("pwm", integer);
}

void StageController::measure()
{
    position = encoder.update(sample_data.channel1) * m_per_count;
    xeno_msg.position = position;
}

int StageController::initialising()
{
    actuate_data = {};
    if (!board_initialised) {
        // This cycle's FPGA exchange ran before the board was initialised: zero the encoder on
        // the next cycle's sample.
        ico_io.init();
        logger.initialise();
        board_initialised = true;
        return 0;
    }
    board_initialised = false;  // a reset initialises the board again
    encoder.zero(sample_data.channel1);
    position = 0.0;
    xeno_msg.position = 0.0;
    evl_printf("stage: initialised, position zeroed\n");
    return 1;
}

int StageController::initialised()
{
    actuate_data = {};
    measure();
    pid.reset(clamp(ros_msg.position_setpoint, position_max) - position);
    return 0;
}

int StageController::run()
{
    logger.start();
    measure();

    double set = clamp(ros_msg.position_setpoint, position_max);
    actuate_data.pwm1 = static_cast<int16_t>(std::lround(pid.update(set - position)));

    log_data = {set, position, actuate_data.pwm1};
    monitor.printf("stage: set %.4f  position %.4f m  pwm %d\n", set, position, actuate_data.pwm1);
    return 0;
}

int StageController::stopping()
{
    actuate_data = {};
    logger.stop();
    return 1;
}

int StageController::stopped()
{
    actuate_data = {};
    measure();
    return 0;
}

int StageController::pausing()
{
    actuate_data = {};
    return 1;
}

int StageController::paused()
{
    actuate_data = {};
    measure();
    pid.reset(clamp(ros_msg.position_setpoint, position_max) - position);
    return 0;
}

int StageController::error()
{
    actuate_data = {};
    return 0;
}
