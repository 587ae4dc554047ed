#ifndef CONTROLLOOP_HPP
#define CONTROLLOOP_HPP

#include "XenoFrt20Sim.hpp"
#include "LoopController.h"

#pragma pack(push, 1)
struct ControlLoopLog
{
    double setpoint_1 = 0.0;
    double position_1 = 0.0;
    double setpoint_2 = 0.0;
    double position_2 = 0.0;
    double steer_1 = 0.0;
    double steer_2 = 0.0;
};
#pragma pack(pop)

class ControlLoop : public XenoFrt20Sim
{
public:
    ControlLoop(unsigned write_decimator_freq, unsigned monitor_freq);

protected:
    // One of these runs per cycle, for the current state: 0 = stay, 1 = state done,
    // negative = go to ERROR (see the base template for what each state is for).
    int initialising() override;
    int initialised() override;
    int run() override;
    int stopping() override;
    int stopped() override;
    int pausing() override;
    int paused() override;
    int error() override;

private:
    // 14-bit encoder count -> continuous count, unwrapping at half the range.
    int unwrap(int raw, int &last, long &turns_offset) const;

    XenoFileHandler file;
    ControlLoopLog log_data;

    LoopController controller;  // the 20-sim generated submodel
    XXDouble u[4] = {0.0, 0.0, 0.0, 0.0};  // SetPoint1, Position1, SetPoint2, Position2
    XXDouble y[2] = {0.0, 0.0};            // Steer1, Steer2 (-1..1)

    bool board_initialised = false;
    int last_raw_1 = 0, last_raw_2 = 0;
    long offset_1 = 0, offset_2 = 0;
};

#endif // CONTROLLOOP_HPP
