#ifndef YOUBOTCONTROLLER_HPP
#define YOUBOTCONTROLLER_HPP

#include "Encoder.hpp"
#include "Pid.hpp"
#include "XenoFrtRosIco.hpp"

#pragma pack(push, 1)
struct YoubotLog {
    double j1 = 0.0, j2 = 0.0, j3 = 0.0, j4 = 0.0, j5 = 0.0;
    double base_vx = 0.0, base_vy = 0.0, base_wz = 0.0;
    int32_t arm_ready = 0;
};
#pragma pack(pop)

// A youBot-like mobile manipulator: a 5-joint arm (channels 1-5: J1 base yaw,
// J2 shoulder, J3 elbow, J4 wrist pitch, J5 wrist roll) on a base of four
// mecanum wheels (channels 6-9: front-left, front-right, rear-left, rear-right).
// The arm falls when its motors are unpowered, so it is held by a control loop
// in every state but STOPPED, and all four states have work to do:
// - INITIALISING moves the arm from its rest pose to its ready pose at a bounded
//   speed and completes only when it is there (so `start` is refused until then);
// - RUN holds the arm and drives the base from Ros2Xeno, but only while the arm
//   reports ready: a base command before that is refused with a message;
// - STOPPING is the closing sequence: the wheels stop, the arm is lowered at a
//   bounded speed onto its rest pose (its joints' stops), then unpowered.
class YoubotController : public XenoFrtRosIco
{
public:
    YoubotController(unsigned cycle_freq, unsigned write_decimator_freq, unsigned monitor_freq);

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
    static constexpr int joints = 5;
    static constexpr int wheels = 4;
    static constexpr int channels = joints + wheels;

    int raw(int ch) const;
    void setPwm(int ch, double pwm);
    void measure();
    void holdArm();
    bool moveArm(const double target[joints], double speed);
    void restArm(const double target[joints]);
    void startMove();
    void stillBase();
    void driveBase();
    void refuseBase();
    bool baseCommanded() const;

    XenoFileHandler file;
    YoubotLog log_data;

    Encoder encoder[channels];
    Pid joint_pid[joints];
    // >>> student part: the template leaves this to the student
    Pid wheel_pid[wheels];
    // <<< student part
    double q[joints] = {};         // measured joint angles, rad
    double reference[joints] = {}; // where the joint PIDs hold the arm, rad
    double wheel[wheels] = {};     // measured wheel angles, rad
    // >>> student part: the template leaves this to the student
    double wheel_reference[wheels] = {};
    // <<< student part
    double dt;

    bool encoders_zeroed = false;
    bool board_initialised = false;
    bool arm_ready = false;
    bool base_refused = false;
    bool at_rest = false;
    unsigned settled_cycles = 0;
    unsigned move_cycles = 0;
};

#endif // YOUBOTCONTROLLER_HPP
