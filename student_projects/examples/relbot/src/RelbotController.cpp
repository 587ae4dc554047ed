#include "RelbotController.hpp"

#include <cmath>

namespace {
constexpr double counts_per_motor_rev = 4096.0;  // 1024-line encoder, quadrature
constexpr double gear_ratio = 15.58;             // motor turns per wheel turn
constexpr double rad_per_count = 2.0 * M_PI / (counts_per_motor_rev * gear_ratio);
constexpr double pwm_limit = 409.0;              // the framework's default 20 % limit

// Gains in PWM counts per rad of wheel-position error (tuned on the simulated RELbot).
constexpr double kp = 2000.0;
constexpr double ki = 500.0;
constexpr double kd = 40.0;
}

RelbotController::RelbotController(unsigned cycle_freq, unsigned write_decimator_freq,
                                   unsigned monitor_freq)
    : XenoFrtRosIco(cycle_freq, write_decimator_freq, monitor_freq, file, &log_data),
      file(true, "logs/relbot", "bin"),
      pid_left(kp, ki, kd, pwm_limit, 1.0 / cycle_freq),
      pid_right(kp, ki, kd, pwm_limit, 1.0 / cycle_freq)
{
    logger.addVariable("setpoint_left", double_);
    logger.addVariable("pos_left", double_);
    logger.addVariable("setpoint_right", double_);
    logger.addVariable("pos_right", double_);
    logger.addVariable("pwm_left", integer);
    logger.addVariable("pwm_right", integer);
}

void RelbotController::measure()
{
    pos_left = encoder_left.update(sample_data.channel1) * rad_per_count;
    // The right encoder counts backwards for forward motion.
    pos_right = -encoder_right.update(sample_data.channel2) * rad_per_count;
    xeno_msg.pos_left = pos_left;
    xeno_msg.pos_right = pos_right;
}

int RelbotController::initialising()
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
    encoder_left.zero(sample_data.channel1);
    encoder_right.zero(sample_data.channel2);
    pos_left = pos_right = 0.0;
    xeno_msg.pos_left = xeno_msg.pos_right = 0.0;
    evl_printf("relbot: initialised, wheel positions zeroed\n");
    return 1;
}

int RelbotController::initialised()
{
    actuate_data = {};
    measure();
    pid_left.reset(ros_msg.steer_left - pos_left);
    pid_right.reset(ros_msg.steer_right - pos_right);
    return 0;
}

int RelbotController::run()
{
    logger.start();
    measure();

    double out_left = pid_left.update(ros_msg.steer_left - pos_left);
    double out_right = pid_right.update(ros_msg.steer_right - pos_right);
    actuate_data.pwm1 = static_cast<int16_t>(std::lround(out_left));
    // The right motor is mirrored: forward needs a negative PWM.
    actuate_data.pwm2 = static_cast<int16_t>(-std::lround(out_right));

    log_data = {ros_msg.steer_left, pos_left, ros_msg.steer_right, pos_right,
                actuate_data.pwm1, actuate_data.pwm2};
    monitor.printf("relbot: set %.3f %.3f  pos %.3f %.3f rad  pwm %d %d\n", ros_msg.steer_left,
                   ros_msg.steer_right, pos_left, pos_right, actuate_data.pwm1, actuate_data.pwm2);
    return 0;
}

int RelbotController::stopping()
{
    actuate_data = {};
    logger.stop();
    return 1;
}

int RelbotController::stopped()
{
    actuate_data = {};
    measure();
    return 0;
}

int RelbotController::pausing()
{
    actuate_data = {};
    return 1;
}

int RelbotController::paused()
{
    actuate_data = {};
    measure();
    // Resume without a derivative kick from the error that built up while paused.
    pid_left.reset(ros_msg.steer_left - pos_left);
    pid_right.reset(ros_msg.steer_right - pos_right);
    return 0;
}

int RelbotController::error()
{
    actuate_data = {};
    return 0;
}
