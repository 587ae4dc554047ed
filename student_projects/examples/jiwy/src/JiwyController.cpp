#include "JiwyController.hpp"

#include <cmath>

namespace {
constexpr double counts_per_motor_rev = 4096.0;  // 1024-line encoder, quadrature
// Camera angle per motor angle: gearbox 1/19, then the belt (pan 1.0, tilt 0.25).
constexpr double pan_ratio = 1.0 / 19.0 * 1.0;
constexpr double tilt_ratio = 1.0 / 19.0 * 0.25;
constexpr double pan_rad_per_count = 2.0 * M_PI / counts_per_motor_rev * pan_ratio;
constexpr double tilt_rad_per_count = 2.0 * M_PI / counts_per_motor_rev * tilt_ratio;
constexpr double pwm_limit = 409.0;  // the framework's default 20 % limit

// Keep setpoints inside the end stops (about +-90 deg pan, +-45 deg tilt) with a margin:
// driving into a stop only heats the motor.
constexpr double pan_max = 80.0 * M_PI / 180.0;
constexpr double tilt_max = 40.0 * M_PI / 180.0;

// Gains in PWM counts per rad of camera-angle error (tuned on the simulated Jiwy).
constexpr double pan_kp = 3000.0, pan_ki = 1000.0, pan_kd = 60.0;
constexpr double tilt_kp = 8000.0, tilt_ki = 3000.0, tilt_kd = 120.0;

double clamp(double v, double lim)
{
    return v > lim ? lim : (v < -lim ? -lim : v);
}
}

JiwyController::JiwyController(unsigned cycle_freq, unsigned write_decimator_freq,
                               unsigned monitor_freq)
    : XenoFrtRosIco(cycle_freq, write_decimator_freq, monitor_freq, file, &log_data),
      file(true, "logs/jiwy", "bin"),
      pid_pan(pan_kp, pan_ki, pan_kd, pwm_limit, 1.0 / cycle_freq),
      pid_tilt(tilt_kp, tilt_ki, tilt_kd, pwm_limit, 1.0 / cycle_freq)
{
    logger.addVariable("pan_setpoint", double_);
    logger.addVariable("pan", double_);
    logger.addVariable("tilt_setpoint", double_);
    logger.addVariable("tilt", double_);
    logger.addVariable("pwm_pan", integer);
    logger.addVariable("pwm_tilt", integer);
}

void JiwyController::measure()
{
    pan = encoder_pan.update(sample_data.channel1) * pan_rad_per_count;
    tilt = encoder_tilt.update(sample_data.channel2) * tilt_rad_per_count;
    xeno_msg.pan = pan;
    xeno_msg.tilt = tilt;
}

int JiwyController::initialising()
{
    actuate_data = {};
    if (!board_initialised) {
        // This cycle's FPGA exchange ran before the board was initialised: zero the
        // encoders on the next cycle's sample.
        ico_io.init();
        logger.initialise();
        board_initialised = true;
        return 0;
    }
    board_initialised = false;  // a reset initialises the board again
    encoder_pan.zero(sample_data.channel1);
    encoder_tilt.zero(sample_data.channel2);
    pan = tilt = 0.0;
    xeno_msg.pan = xeno_msg.tilt = 0.0;
    evl_printf("jiwy: initialised, camera angles zeroed\n");
    return 1;
}

int JiwyController::initialised()
{
    actuate_data = {};
    measure();
    pid_pan.reset(clamp(ros_msg.pan_setpoint, pan_max) - pan);
    pid_tilt.reset(clamp(ros_msg.tilt_setpoint, tilt_max) - tilt);
    return 0;
}

int JiwyController::run()
{
    logger.start();
    measure();

    double pan_set = clamp(ros_msg.pan_setpoint, pan_max);
    double tilt_set = clamp(ros_msg.tilt_setpoint, tilt_max);
    actuate_data.pwm1 = static_cast<int16_t>(std::lround(pid_pan.update(pan_set - pan)));
    actuate_data.pwm2 = static_cast<int16_t>(std::lround(pid_tilt.update(tilt_set - tilt)));

    log_data = {pan_set, pan, tilt_set, tilt, actuate_data.pwm1, actuate_data.pwm2};
    monitor.printf("jiwy: set %.3f %.3f  angle %.3f %.3f rad  pwm %d %d\n", pan_set, tilt_set, pan,
                   tilt, actuate_data.pwm1, actuate_data.pwm2);
    return 0;
}

int JiwyController::stopping()
{
    actuate_data = {};
    logger.stop();
    return 1;
}

int JiwyController::stopped()
{
    actuate_data = {};
    measure();
    return 0;
}

int JiwyController::pausing()
{
    actuate_data = {};
    return 1;
}

int JiwyController::paused()
{
    actuate_data = {};
    measure();
    pid_pan.reset(clamp(ros_msg.pan_setpoint, pan_max) - pan);
    pid_tilt.reset(clamp(ros_msg.tilt_setpoint, tilt_max) - tilt);
    return 0;
}

int JiwyController::error()
{
    actuate_data = {};
    return 0;
}
