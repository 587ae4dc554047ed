#include "Template.hpp"

#include <xrf/tunable.hpp>

namespace {
// A value the dashboard, `xrf param set` and ROS 2 can change while the controller runs
// (docs/students/tuning.md): name, default, min, max, unit. Read it like a double.
xrf::Tunable echo_gain{"echo.gain", 1.0, -10.0, 10.0, "-"};
}

Template::Template(unsigned cycle_freq, unsigned write_decimator_freq, unsigned monitor_freq)
    : XenoFrtRosIco(cycle_freq, write_decimator_freq, monitor_freq, file, &log_data),
      file(true, "logs/template", "bin")
{
    // One addVariable per field of TemplateLog, in the same order.
    logger.addVariable("encoder_left", integer);
    logger.addVariable("encoder_right", integer);
    logger.addVariable("steer_left", double_);
    logger.addVariable("steer_right", double_);
}

// INITIALISING: bring the hardware and your controller into a known state. Runs every cycle
// until it returns 1 (then INITIALISED); also entered again after a reset command.
int Template::initialising()
{
    ico_io.init();          // INIT the FPGA (a missing board is fatal)
    logger.initialise();    // writes the log header once; safe to call again after reset
    actuate_data = {};      // all PWM 0, all digital outputs off
    return 1;
}

// INITIALISED: ready and waiting for the start command. Keep the outputs safe.
int Template::initialised()
{
    return 0;
}

// RUN: the controller, once per cycle. sample_data holds this cycle's encoders and inputs,
// ros_msg the latest setpoints; what you put in actuate_data is sent at the next cycle's
// start, xeno_msg goes to the host at the write-decimator rate.
int Template::run()
{
    logger.start();

    log_data.encoder_left = sample_data.channel1;
    log_data.encoder_right = sample_data.channel2;
    log_data.steer_left = ros_msg.steer_left;
    log_data.steer_right = ros_msg.steer_right;

    // Placeholder: echo the setpoints back (times a tunable gain) and drive no motor. Replace with your controller.
    xeno_msg.pos_left = ros_msg.steer_left;
    xeno_msg.pos_right = ros_msg.steer_right;
    xeno_msg.pos_left *= echo_gain;
    xeno_msg.pos_right *= echo_gain;
    actuate_data.pwm1 = 0;
    actuate_data.pwm2 = 0;

    monitor.printf("run: enc %d %d  setpoints %.3f %.3f\n", sample_data.channel1,
                   sample_data.channel2, ros_msg.steer_left, ros_msg.steer_right);
    return 0;
}

// STOPPING: bring the plant to rest (ramp down, park). Return 1 when it is safe: STOPPED.
int Template::stopping()
{
    actuate_data = {};
    logger.stop();
    return 1;
}

// STOPPED: at rest; from here the host may reset (INITIALISING) or quit.
int Template::stopped()
{
    actuate_data = {};
    return 0;
}

// PAUSING: hold still for a while (start resumes RUN). Return 1 when paused.
int Template::pausing()
{
    actuate_data = {};
    return 1;
}

// PAUSED: hold still until start (RUN), stop or reset.
int Template::paused()
{
    actuate_data = {};
    return 0;
}

// ERROR: entered when a hook returned a negative number; keep the outputs safe. The host
// may reset or quit.
int Template::error()
{
    actuate_data = {};
    return 0;
}
