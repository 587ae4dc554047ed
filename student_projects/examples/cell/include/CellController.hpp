#ifndef CELLCONTROLLER_HPP
#define CELLCONTROLLER_HPP

#include "Encoder.hpp"
// >>> student part: the template leaves this to the student
#include "Pid.hpp"
// <<< student part
#include "XenoFrtRosIco.hpp"

#pragma pack(push, 1)
struct CellLog {
    double table_setpoint = 0.0, press_setpoint = 0.0, feeder_setpoint = 0.0;
    double table = 0.0, press = 0.0, feeder = 0.0;
};
#pragma pack(pop)

// A production cell of three axes, each with a relative encoder and a home
// switch: channel 1 = the rotary table (rad), 2 = the press ram (m), 3 = the
// feeder arm (m). Nothing says where an axis is at power-up, so INITIALISING
// homes every axis on its switch (input pin 1 of its channel) and zeroes its
// encoder there; initialising() completes only when all three are homed, so the
// framework refuses `start` until then (START is not allowed in INITIALISING).
class CellController : public XenoFrtRosIco
{
public:
    CellController(unsigned cycle_freq, unsigned write_decimator_freq, unsigned monitor_freq);

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
    static constexpr int axes = 3;
    enum class Homing { leave_switch, seek_switch, homed };

    struct Axis {
        Encoder encoder;
        Homing phase = Homing::leave_switch;
        double position = 0.0; // rad or m from the switch edge
    };

    int raw(int i) const;
    bool home_switch(int i) const;
    void measure();
    void setPwm(int i, double pwm);
    void setpoints(double set[axes]) const;

    XenoFileHandler file;
    CellLog log_data;

    Axis axis[axes];
    // >>> student part: the template leaves this to the student
    Pid pid[axes];
    // <<< student part
    bool homed = false;
    bool board_initialised = false;
    unsigned homing_cycles = 0;
};

#endif // CELLCONTROLLER_HPP
