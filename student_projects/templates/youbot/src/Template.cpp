#include "Template.hpp"

#include <cmath>

namespace
{
constexpr double counts_per_motor_rev = 4096.0; // 1024-line encoder, quadrature
constexpr double two_pi = 6.283185307179586;
constexpr double deg = two_pi / 360.0;
// Joint gears (motor turns per joint turn), J1..J5, and the wheels' (the youBot
// manual's, rounded).
constexpr double joint_gear[5] = {156.0, 156.0, 100.0, 71.0, 71.0};
constexpr double wheel_gear = 26.0;
// The rest pose: the arm folded onto its joints' stops, where gravity keeps it
// unpowered. The arm is parked there at power-up, so the encoders' zero is this
// pose (J1 and J5 carry no load: 0 there).
constexpr double rest_pose[5] = {0.0, -65.0 * deg, 151.0 * deg, -102.5 * deg, 0.0};
// The ready pose: the arm raised, folded over the base, clear of the floor.
constexpr double ready_pose[5] = {0.0, 10.0 * deg, 60.0 * deg, 40.0 * deg, 0.0};
// Joint speeds of the two moves: rising to ready, and lowering to rest in the
// closing sequence (slow enough that a person sees it coming).
constexpr double ready_speed = 30.0 * deg;
constexpr double closing_speed = 20.0 * deg;
// "There": every joint within 2° of its target for 0.2 s. Readiness is lost in
// RUN when a joint is pushed 10° off (then the base stops) and regained within
// 2°.
constexpr double at_target = 2.0 * deg;
constexpr double lost_ready = 10.0 * deg;
constexpr unsigned settle_cycles_needed = 200; // at 1 kHz
// A move not done in this long is a jammed or overloaded arm: ERROR.
constexpr unsigned move_timeout_s = 20;
constexpr double pwm_limit = 409.0; // the framework's default 20 % limit
// Joint PID gains in PWM counts per rad of joint error: each critically damped
// with its motor's back-EMF on the simulated arm (docs/rt_core/simulator.md);
// the integral takes up the gravity load.
constexpr double joint_kp[5] = {3000.0, 4000.0, 3000.0, 2000.0, 1000.0};
constexpr double joint_ki[5] = {3000.0, 6000.0, 4000.0, 2000.0, 500.0};
constexpr double joint_kd[5] = {30.0, 40.0, 30.0, 10.0, 5.0};
// Base: wheel radius, half wheel base + half track (m), speed limits.
constexpr double wheel_radius = 0.05;
constexpr double half_base_plus_track = 0.236 + 0.150;
constexpr double max_speed = 0.2; // m/s
constexpr double max_turn = 0.5;  // rad/s

double clamp(double v, double lo, double hi)
{
    return v > hi ? hi : (v < lo ? lo : v);
}
} // namespace

Template::Template(unsigned cycle_freq, unsigned write_decimator_freq, unsigned monitor_freq)
    : XenoFrtRosIco(cycle_freq, write_decimator_freq, monitor_freq, file, &log_data),
      file(true, "logs/template_youbot", "bin"),
      joint_pid{Pid(joint_kp[0], joint_ki[0], joint_kd[0], pwm_limit, 1.0 / cycle_freq),
                Pid(joint_kp[1], joint_ki[1], joint_kd[1], pwm_limit, 1.0 / cycle_freq),
                Pid(joint_kp[2], joint_ki[2], joint_kd[2], pwm_limit, 1.0 / cycle_freq),
                Pid(joint_kp[3], joint_ki[3], joint_kd[3], pwm_limit, 1.0 / cycle_freq),
                Pid(joint_kp[4], joint_ki[4], joint_kd[4], pwm_limit, 1.0 / cycle_freq)},
      dt(1.0 / cycle_freq)
{
    logger.addVariable("j1", double_);
    logger.addVariable("j2", double_);
    logger.addVariable("j3", double_);
    logger.addVariable("j4", double_);
    logger.addVariable("j5", double_);
    logger.addVariable("base_vx", double_);
    logger.addVariable("base_vy", double_);
    logger.addVariable("base_wz", double_);
    logger.addVariable("arm_ready", integer);
}

// Channel ch + 1's encoder and PWM. An ico board carries four channels: board 0
// (channels 1-4) is XRF2's sample_data / actuate_data, the bench's further
// boards (channels 5-8, 9-12) are XRF Lab's sample_more[b - 1] / actuate_more[b
// - 1].
int Template::raw(int ch) const
{
    const IcoIo::IcoRead &in = ch < 4 ? sample_data : sample_more[ch / 4 - 1];
    switch (ch % 4) {
    case 0:
        return in.channel1;
    case 1:
        return in.channel2;
    case 2:
        return in.channel3;
    default:
        return in.channel4;
    }
}

void Template::setPwm(int ch, double pwm)
{
    int16_t v = static_cast<int16_t>(std::lround(clamp(pwm, -pwm_limit, pwm_limit)));
    IcoIo::IcoWrite &out = ch < 4 ? actuate_data : actuate_more[ch / 4 - 1];
    switch (ch % 4) {
    case 0:
        out.pwm1 = v;
        break;
    case 1:
        out.pwm2 = v;
        break;
    case 2:
        out.pwm3 = v;
        break;
    default:
        out.pwm4 = v;
        break;
    }
}

void Template::measure()
{
    for (int j = 0; j < joints; j++)
        q[j] = rest_pose[j] +
               encoder[j].update(raw(j)) * two_pi / counts_per_motor_rev / joint_gear[j];
    for (int w = 0; w < wheels; w++)
        wheel[w] = encoder[joints + w].update(raw(joints + w)) * two_pi / counts_per_motor_rev /
                   wheel_gear;
    xeno_msg.j1 = q[0];
    xeno_msg.j2 = q[1];
    xeno_msg.j3 = q[2];
    xeno_msg.j4 = q[3];
    xeno_msg.j5 = q[4];
    xeno_msg.arm_ready = arm_ready;
    xeno_msg.base_refused = base_refused;
    log_data = {q[0],
                q[1],
                q[2],
                q[3],
                q[4],
                ros_msg.base_vx,
                ros_msg.base_vy,
                ros_msg.base_wz,
                arm_ready ? 1 : 0};
}

void Template::holdArm()
{
    for (int j = 0; j < joints; j++)
        setPwm(j, joint_pid[j].update(reference[j] - q[j]));
}

// Move the held reference towards `target` at `speed` (rad/s per joint) and
// hold the arm on it; true once the arm has been at the target for settle time.
bool Template::moveArm(const double target[joints], double speed)
{
    bool there = true;
    for (int j = 0; j < joints; j++) {
        reference[j] += clamp(target[j] - reference[j], -speed * dt, speed * dt);
        there = there && reference[j] == target[j] && std::fabs(q[j] - target[j]) < at_target;
    }
    holdArm();
    settled_cycles = there ? settled_cycles + 1 : 0;
    return settled_cycles >= settle_cycles_needed;
}

// The closing sequence's end: at rest the joints lean on their stops under
// gravity, so the arm is unpowered there.
void Template::restArm(const double target[joints])
{
    if (!at_rest && moveArm(target, closing_speed)) {
        at_rest = true;
        evl_printf("youbot: arm at rest, unpowered\n");
    }
    if (at_rest)
        for (int j = 0; j < joints; j++)
            setPwm(j, 0.0);
}

// A move starts from where the arm is: no jump in the held reference.
void Template::startMove()
{
    for (int j = 0; j < joints; j++) {
        reference[j] = q[j];
        joint_pid[j].reset(0.0);
    }
    settled_cycles = 0;
    move_cycles = 0;
}

bool Template::baseCommanded() const
{
    return ros_msg.base_vx != 0.0 || ros_msg.base_vy != 0.0 || ros_msg.base_wz != 0.0;
}

void Template::stillBase()
{
    // >>> student part: the template leaves this to the student
    // TODO: reset your base controller's state (references, integrators) here.
    for (int w = 0; w < wheels; w++)
        setPwm(joints + w, 0.0);
    // <<< student part
}

// A base command while the arm is not ready: the wheels stay still, and the
// refusal is said once per command (base_refused stays up while it lasts).
void Template::refuseBase()
{
    bool commanded = baseCommanded();
    if (commanded && !base_refused)
        evl_printf("youbot: base command refused: the arm is not ready\n");
    base_refused = commanded;
}

// RUN, with the arm ready: drive the base from ros_msg.base_vx, base_vy (m/s,
// forward and to the left) and base_wz (rad/s, counter-clockwise). TODO: the
// mecanum inverse kinematics (wheel speeds from the base's velocity; wheel
// radius and half_base_plus_track above), then a PWM per wheel with
// setPwm(joints + w, value) (w = 0..3: front-left, front-right, rear-left,
// rear-right), from its speed and its measured angle wheel[w] (rad). As given,
// the base stays still.
void Template::driveBase()
{
    // >>> student part: the template leaves this to the student
    for (int w = 0; w < wheels; w++)
        setPwm(joints + w, 0.0);
    // <<< student part
}

int Template::initialising()
{
    if (!board_initialised) {
        ico_io.init();
        if (!logger.isInitialised())
            logger.initialise();
        logger.start(); // from the first move on: the log holds the rise and the
                        // closing sequence
        board_initialised = true;
        if (!encoders_zeroed) {
            // Power-up: the arm is parked at rest, where the counters read zero.
            for (int ch = 0; ch < channels; ch++)
                encoder[ch].zero(raw(ch));
            encoders_zeroed = true;
        }
        arm_ready = false;
        at_rest = false;
        measure();
        startMove();
        evl_printf("youbot: moving the arm to its ready pose\n");
        return 0;
    }
    measure();
    refuseBase();
    stillBase();
    if (++move_cycles > move_timeout_s * 1000u) {
        evl_printf("youbot: the arm did not reach its ready pose in %u s\n", move_timeout_s);
        board_initialised = false;
        return -1; // error() lowers it
    }
    if (!moveArm(ready_pose, ready_speed))
        return 0;
    arm_ready = true;
    board_initialised = false; // a reset initialises the board again
    measure();
    evl_printf("youbot: arm ready\n");
    return 1;
}

int Template::initialised()
{
    measure();
    holdArm();            // the arm would fall: it is held in every state but STOPPED
    base_refused = false; // the arm is ready: RUN will take base commands
    stillBase();
    return 0;
}

int Template::run()
{
    measure();
    holdArm();
    bool off = false, on = true;
    for (int j = 0; j < joints; j++) {
        double e = std::fabs(q[j] - reference[j]);
        off = off || e > lost_ready;
        on = on && e < at_target;
    }
    if (arm_ready && off) {
        arm_ready = false;
        evl_printf("youbot: arm pushed off its ready pose: base stopped\n");
    } else if (!arm_ready && on) {
        arm_ready = true;
        evl_printf("youbot: arm ready again\n");
    }
    if (arm_ready) {
        base_refused = false;
        driveBase();
    } else {
        refuseBase();
        stillBase();
    }
    monitor.printf("youbot: J1..J5 %.2f %.2f %.2f %.2f %.2f rad  base %.2f %.2f %.2f\n", q[0], q[1],
                   q[2], q[3], q[4], ros_msg.base_vx, ros_msg.base_vy, ros_msg.base_wz);
    return 0;
}

// The closing sequence: wheels still, the arm lowered onto its rest pose at a
// bounded speed and unpowered there; STOPPED follows only then.
int Template::stopping()
{
    if (arm_ready) {
        arm_ready = false;
        measure();
        startMove();
        evl_printf("youbot: closing: lowering the arm to rest\n");
    }
    measure();
    refuseBase();
    stillBase();
    if (++move_cycles > move_timeout_s * 1000u) {
        evl_printf("youbot: the arm did not reach rest in %u s\n", move_timeout_s);
        return -1; // error() keeps lowering it
    }
    restArm(rest_pose);
    return at_rest ? 1 : 0;
}

int Template::stopped()
{
    actuate_data = {}; // at rest on its stops: safe unpowered
    measure();
    refuseBase();
    return 0;
}

int Template::pausing()
{
    measure();
    holdArm();
    stillBase();
    return 1;
}

int Template::paused()
{
    measure();
    holdArm();
    stillBase();
    return 0;
}

// Whatever went wrong, the arm is not dropped: it is lowered to rest as in the
// closing sequence, then unpowered.
int Template::error()
{
    if (arm_ready || move_cycles > move_timeout_s * 1000u) {
        arm_ready = false;
        measure();
        startMove();
    }
    measure();
    refuseBase();
    stillBase();
    restArm(rest_pose);
    return 0;
}
