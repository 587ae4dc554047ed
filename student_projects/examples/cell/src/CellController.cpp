#include "CellController.hpp"

#include <cmath>

namespace
{
constexpr double counts_per_motor_rev = 4096.0; // 1024-line encoder, quadrature
constexpr double two_pi = 6.283185307179586;
// Load units (rad of table, m of ram or carriage) per encoder count: table 50:1
// worm gear, press 4 mm lead screw, feeder 8 mm lead screw.
constexpr double unit_per_count[3] = {two_pi / counts_per_motor_rev / 50.0,
                                      0.004 / counts_per_motor_rev, 0.008 / counts_per_motor_rev};
// Setpoints stay inside the travel past the switch edge with a margin (table
// 270°, press 150 mm, feeder 200 mm, each less its switch zone at both ends).
constexpr double set_max[3] = {4.4, 0.135, 0.185};
constexpr double pwm_limit = 409.0; // the framework's default 20 % limit
// Homing speed: slow enough that the switch edge is met within a count or so
// per cycle, fast enough that the longest axis (the table, 270°) homes in a few
// seconds.
constexpr double homing_pwm = 300.0;
// A switch not found in this long is a broken switch or a jammed axis: ERROR,
// not a run away.
constexpr unsigned homing_timeout_s = 20;
// >>> student part: the template leaves this to the student
// PID gains in PWM counts per load unit of error (per rad for the table, per m
// otherwise), scaled from the stage example's by each axis's load units per
// motor radian.
constexpr double kp[3] = {2500.0, 80000.0, 40000.0};
constexpr double ki[3] = {5000.0, 160000.0, 80000.0};
constexpr double kd[3] = {50.0, 1600.0, 800.0};
// <<< student part

double clamp(double v, double lo, double hi)
{
    return v > hi ? hi : (v < lo ? lo : v);
}
} // namespace

CellController::CellController(unsigned cycle_freq, unsigned write_decimator_freq,
                               unsigned monitor_freq)
    : XenoFrtRosIco(cycle_freq, write_decimator_freq, monitor_freq, file, &log_data),
      file(true, "logs/cell", "bin"),
      // >>> student part: the template leaves this to the student
      pid{Pid(kp[0], ki[0], kd[0], pwm_limit, 1.0 / cycle_freq),
          Pid(kp[1], ki[1], kd[1], pwm_limit, 1.0 / cycle_freq),
          Pid(kp[2], ki[2], kd[2], pwm_limit, 1.0 / cycle_freq)}
// <<< student part
{
    logger.addVariable("table_setpoint", double_);
    logger.addVariable("press_setpoint", double_);
    logger.addVariable("feeder_setpoint", double_);
    logger.addVariable("table", double_);
    logger.addVariable("press", double_);
    logger.addVariable("feeder", double_);
}

int CellController::raw(int i) const
{
    return i == 0 ? sample_data.channel1 : (i == 1 ? sample_data.channel2 : sample_data.channel3);
}

bool CellController::home_switch(int i) const
{
    return i == 0 ? sample_data.channel1_1
                  : (i == 1 ? sample_data.channel2_1 : sample_data.channel3_1);
}

void CellController::setPwm(int i, double pwm)
{
    int16_t v = static_cast<int16_t>(std::lround(clamp(pwm, -pwm_limit, pwm_limit)));
    if (i == 0)
        actuate_data.pwm1 = v;
    else if (i == 1)
        actuate_data.pwm2 = v;
    else
        actuate_data.pwm3 = v;
}

void CellController::measure()
{
    for (int i = 0; i < axes; i++)
        axis[i].position = axis[i].encoder.update(raw(i)) * unit_per_count[i];
    xeno_msg.table = axis[0].position;
    xeno_msg.press = axis[1].position;
    xeno_msg.feeder = axis[2].position;
    xeno_msg.homed = homed;
}

void CellController::setpoints(double set[axes]) const
{
    set[0] = clamp(ros_msg.table_setpoint, 0.0, set_max[0]);
    set[1] = clamp(ros_msg.press_setpoint, 0.0, set_max[1]);
    set[2] = clamp(ros_msg.feeder_setpoint, 0.0, set_max[2]);
}

int CellController::initialising()
{
    actuate_data = {};
    if (!board_initialised) {
        // Every (re-)initialisation homes again: after a reset nothing says the
        // axes stayed put.
        ico_io.init();
        logger.initialise();
        board_initialised = true;
        homed = false;
        homing_cycles = 0;
        for (int i = 0; i < axes; i++) {
            axis[i].phase = Homing::leave_switch;
            axis[i].encoder.zero(raw(i));
        }
        measure();
        return 0;
    }
    measure();
    if (++homing_cycles > homing_timeout_s * 1000u) {
        evl_printf("cell: homing found no switch in %u s: a broken switch or a "
                   "jammed axis\n",
                   homing_timeout_s);
        board_initialised = false;
        return -1;
    }
    int done = 0;
    for (int i = 0; i < axes; i++) {
        Axis &a = axis[i];
        switch (a.phase) {
        case Homing::leave_switch:
            // Started on the switch: move off it first, so the edge is always met
            // from above.
            if (home_switch(i))
                setPwm(i, homing_pwm);
            else
                a.phase = Homing::seek_switch;
            break;
        case Homing::seek_switch:
            if (home_switch(i)) {
                // The switch's edge is the axis's zero: this cycle's count is position
                // 0.
                a.encoder.zero(raw(i));
                a.position = 0.0;
                a.phase = Homing::homed;
                evl_printf("cell: axis %d homed\n", i + 1);
            } else {
                setPwm(i, -homing_pwm);
            }
            break;
        case Homing::homed:
            done++;
            break;
        }
    }
    if (done < axes)
        return 0;
    homed = true;
    board_initialised = false; // a reset initialises the board again
    measure();
    evl_printf("cell: all axes homed\n");
    return 1;
}

int CellController::initialised()
{
    actuate_data = {};
    measure();
    // >>> student part: the template leaves this to the student
    double set[axes];
    setpoints(set);
    for (int i = 0; i < axes; i++)
        pid[i].reset(set[i] - axis[i].position);
    // <<< student part
    return 0;
}

int CellController::run()
{
    logger.start();
    measure();
    if (!homed) {
        // Cannot happen through the state machine (RUN follows INITIALISED only);
        // never move an axis whose zero is unknown.
        actuate_data = {};
        return -1;
    }
    double set[axes];
    setpoints(set);
    // >>> student part: the template leaves this to the student
    for (int i = 0; i < axes; i++)
        setPwm(i, pid[i].update(set[i] - axis[i].position));
    // <<< student part

    log_data = {set[0], set[1], set[2], axis[0].position, axis[1].position, axis[2].position};
    monitor.printf("cell: table %.3f rad  press %.4f m  feeder %.4f m\n", axis[0].position,
                   axis[1].position, axis[2].position);
    return 0;
}

int CellController::stopping()
{
    actuate_data = {};
    logger.stop();
    return 1;
}

int CellController::stopped()
{
    actuate_data = {};
    measure();
    return 0;
}

int CellController::pausing()
{
    actuate_data = {};
    return 1;
}

int CellController::paused()
{
    actuate_data = {};
    measure();
    // >>> student part: the template leaves this to the student
    double set[axes];
    setpoints(set);
    for (int i = 0; i < axes; i++)
        pid[i].reset(set[i] - axis[i].position);
    // <<< student part
    return 0;
}

int CellController::error()
{
    actuate_data = {};
    return 0;
}
