#ifndef STAGECONTROLLER_HPP
#define STAGECONTROLLER_HPP

#include "XenoFrtRosIco.hpp"
#include "Encoder.hpp"
#include "Pid.hpp"

#pragma pack(push, 1)
struct StageLog {
    double position_setpoint = 0.0;
    double position = 0.0;
    int pwm = 0;
};
#pragma pack(pop)

// Position control of a one-axis linear stage: channel 1 = the lead-screw motor. Positions are
// of the carriage, in m, zero where it was at initialisation.
class StageController : public XenoFrtRosIco
{
public:
    StageController(unsigned cycle_freq, unsigned write_decimator_freq, unsigned monitor_freq);

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
    StageLog log_data;

    Encoder encoder;
    Pid pid;
    double position = 0.0; // m
    bool board_initialised = false;
};

#endif // STAGECONTROLLER_HPP
