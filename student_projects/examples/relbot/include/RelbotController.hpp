#ifndef RELBOTCONTROLLER_HPP
#define RELBOTCONTROLLER_HPP

#include "XenoFrtRosIco.hpp"
#include "Encoder.hpp"
#include "Pid.hpp"

#pragma pack(push, 1)
struct RelbotLog {
    double setpoint_left = 0.0;
    double pos_left = 0.0;
    double setpoint_right = 0.0;
    double pos_right = 0.0;
    int pwm_left = 0;
    int pwm_right = 0;
};
#pragma pack(pop)

// Wheel position control for the RELbot: channel 1 = left wheel, channel 2 = right wheel.
// The right motor is mounted mirrored, so its encoder counts backwards and it needs a
// negative PWM to drive forward; this class hides both so that host-side setpoints and
// measurements are "positive = forward" for both wheels.
class RelbotController : public XenoFrtRosIco
{
public:
    RelbotController(unsigned cycle_freq, unsigned write_decimator_freq, unsigned monitor_freq);

protected:
    int initialising() override;
    int initialised() override;
    int run() override;
    int stopping() override;
    int stopped() override;
    int pausing() override;
    int paused() override;
    int error() override;

private:
    void measure();

    XenoFileHandler file;
    RelbotLog log_data;

    Encoder encoder_left, encoder_right;
    Pid pid_left, pid_right;
    double pos_left = 0.0, pos_right = 0.0; // rad at the wheel, forward positive
    bool board_initialised = false;
};

#endif // RELBOTCONTROLLER_HPP
