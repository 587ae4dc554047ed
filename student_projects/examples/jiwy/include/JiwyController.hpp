#ifndef JIWYCONTROLLER_HPP
#define JIWYCONTROLLER_HPP

#include "XenoFrtRosIco.hpp"
#include "Encoder.hpp"
#include "Pid.hpp"

#pragma pack(push, 1)
struct JiwyLog {
    double pan_setpoint = 0.0;
    double pan = 0.0;
    double tilt_setpoint = 0.0;
    double tilt = 0.0;
    int pwm_pan = 0;
    int pwm_tilt = 0;
};
#pragma pack(pop)

// Pan/tilt position control for the Jiwy camera: channel 1 = pan, channel 2 = tilt.
// Angles are at the camera (after gearbox and belt), zero where the camera was at
// initialisation.
class JiwyController : public XenoFrtRosIco
{
public:
    JiwyController(unsigned cycle_freq, unsigned write_decimator_freq, unsigned monitor_freq);

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
    JiwyLog log_data;

    Encoder encoder_pan, encoder_tilt;
    Pid pid_pan, pid_tilt;
    double pan = 0.0, tilt = 0.0; // rad at the camera
    bool board_initialised = false;
};

#endif // JIWYCONTROLLER_HPP
