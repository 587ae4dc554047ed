// xrf/tunable.hpp — a value a controller lets the dashboard, the CLI and ROS 2 tune while it runs
// (docs/students/tuning.md). Header-only for the student: include it and declare
//
//     static xrf::Tunable kp{"pid.kp", 1.0, 0.0, 20.0, "-/rad"};   // name, default, min, max, unit
//     ...
//     double steer = kp * error;                                 // reads the current value
//
// A Tunable must exist before loop() starts (a global, a static, or a member of the loop
// object): the runtime lists it in the run's parameter table when the loop starts. The loop
// thread writes a new value at a cycle boundary, before the controller's hook runs, so the
// controller reads a value that does not change during its cycle; no lock is involved.
//
// 20-sim controllers need nothing of this: their parameters (m_P[] of the generated submodel,
// named in <Submodel>_tokens.xml) are found by the build.
#pragma once

#include <cstdint>

namespace xrf
{

// Registration, before loop() (the runtime prints and leaves out a bad or surplus one at start).
void registerTunable(const char *name, double *value, double def, double min, double max,
                     const char *unit);
// For the code the build generates from a 20-sim export (the parameter table and the submodel
// objects whose m_P[] it tunes); not for students' code.
void register20simTable(const char *const *names, const double *defaults, const char *const *units,
                        uint32_t count);
void register20simModel(double **parameters, const int *count);

class Tunable
{
public:
    Tunable(const char *name, double def, double min, double max, const char *unit = "")
        : value_(def)
    {
        registerTunable(name, &value_, def, min, max, unit);
    }
    Tunable(const Tunable &) = delete; // the runtime holds this object's address
    Tunable &operator=(const Tunable &) = delete;

    double get() const { return value_; }
    operator double() const { return value_; }

private:
    double value_; // written only by the loop thread, between two cycles
};

} // namespace xrf
