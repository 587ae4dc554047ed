/*
 * plant_youbot.c — a youBot-like mobile manipulator (after the thesis's youBot use case,
 * USE_CASES.md): a 5-joint arm whose links fall under gravity when their motors are unpowered,
 * on a base with four mecanum wheels. The arm is why the bench's safe reaction is `hold`
 * (xrf/hold.h): zero volts here lets the shoulder fall at ~15 °/s, onto whatever is below.
 *
 * Channels (agreed with the app side: profile, 3D view, example): 1 J1 base yaw, 2 J2 shoulder
 * pitch, 3 J3 elbow pitch, 4 J4 wrist pitch, 5 J5 wrist roll; 6..9 the wheels front-left,
 * front-right, rear-left, rear-right. Each channel's encoder is on its motor shaft. Positive duty
 * turns a joint positive and rolls a wheel forward.
 *
 * Joint angles: 0 is the arm pointing straight up ("candle"), a positive pitch leans the link
 * forward (+x of the base). The pitch joints J2..J4 form a planar chain in the vertical plane J1
 * turns; gravity acts on them, not on J1 (yaw) or J5 (roll about the last link).
 *
 * Each joint is its motor (plant.h's DC model) through a gear to the link: the link's inertia is
 * reflected to the motor as a constant (the pose-dependent coupling between joints is left out:
 * the gravity torques, which are what matter for holding and dropping, are coupled exactly). The
 * base's wheels each carry a quarter of its mass; odometry integrates the mecanum kinematics.
 *
 * Figures: gear ratios, joint ranges, link lengths, wheel size and wheel base are the KUKA
 * youBot's as its user manual gives them (rounded); link masses and centres, motor constants and
 * frictions are assumptions of the same order (docs/rt_core/simulator.md, ../shared/PLANTS.md).
 */
#include "plant.h"
#include "xrf/hold.h"

#ifndef M_PI
#define M_PI 3.14159265358979323846
#endif

#define DEG (M_PI / 180.0)
#define YB_JOINTS 5
#define YB_WHEELS 4
#define YB_CHANNELS (YB_JOINTS + YB_WHEELS)
#define YB_SUPPLY_V 24.0 /* youBot: 24 V bus (manual) */
#define YB_G 9.81

/* Links of the pitch chain, from the manual: J2->J3 155 mm, J3->J4 135 mm, J4 -> gripper tip
 * 218 mm (J5 and the gripper included). Masses and centres: assumed (the arm is 6.3 kg in all,
 * the manual; J1's turning part and the base link take the rest). */
#define YB_L2 0.155
#define YB_L3 0.135
#define YB_M2 1.3
#define YB_C2 0.080
#define YB_M3 1.0
#define YB_C3 0.070
#define YB_M4 0.9
#define YB_C4 0.100

/* Base: 100 mm wheels, 26:1 gear, half the wheel base and half the track (manual, rounded);
 * 20 kg (manual: ~20 kg without the arm). */
#define YB_WHEEL_R 0.050
#define YB_WHEEL_GEAR 26.0
#define YB_LX 0.236
#define YB_LY 0.150
#define YB_BASE_KG 20.0

struct youbot_joint {
    struct xrf_dc_motor_params p;
    double gear;
    double lo, hi; /* hard stops, rad at the joint */
    struct xrf_dc_motor m;
};

struct youbot {
    double supply_v;
    struct youbot_joint j[YB_JOINTS];
    struct xrf_dc_motor_params wp; /* every wheel's motor */
    struct xrf_dc_motor w[YB_WHEELS];
    double x, y, theta; /* base pose in the start frame: m, m, rad */
};

/* The gravity torque on J2..J4 at pose q (J1, J5: none), the one model both the plant and the
 * hold law use: x_k is the horizontal reach of link k's centre from J2. */
static void youbot_gravity(const double *q, double *tau)
{
    double p2 = q[1], p3 = q[1] + q[2], p4 = q[1] + q[2] + q[3];
    double j3 = YB_L2 * sin(p2);
    double j4 = j3 + YB_L3 * sin(p3);
    double x2 = YB_C2 * sin(p2), x3 = j3 + YB_C3 * sin(p3), x4 = j4 + YB_C4 * sin(p4);
    tau[0] = 0.0;
    tau[1] = YB_G * (YB_M2 * x2 + YB_M3 * x3 + YB_M4 * x4);
    tau[2] = YB_G * (YB_M3 * (x3 - j3) + YB_M4 * (x4 - j3));
    tau[3] = YB_G * YB_M4 * (x4 - j4);
    tau[4] = 0.0;
}

/* Motor: an assumed 24 V brushless drive of the size the youBot uses (~0.03 N·m/A, 1 ohm),
 * 135 g·cm² rotor; the gear's Coulomb friction at the motor is assumed small enough that the
 * arm is not self-locking (the use case: it collapses unpowered). */
#define YB_MOTOR_K 0.03
#define YB_MOTOR_R 1.0
static const struct xrf_dc_motor_params YB_MOTOR = {
    .k = YB_MOTOR_K, .r = YB_MOTOR_R, .j = 1.35e-5, .b = 1.0e-5, .tc = 5.0e-3};

/* The rest pose: the arm folded with every pitch joint leaning on a hard stop under its own
 * weight (J2 back on -65°, J3 forward on +151°, J4 back on -102.5°: the gravity torques there
 * all push into the stops, checked by the unit test), so zero volts there drops nothing. J1 and
 * J5 carry no gravity: they stay where they are held (NAN). */
#define YB_REST_J2 (-65.0 * DEG)
#define YB_REST_J3 (151.0 * DEG)
#define YB_REST_J4 (-102.5 * DEG)

/* The joints, one row each: gear ratio and range of the manual (its zero moved to the candle
 * pose); the link inertia about the joint with the arm stretched (assumed: the worst case); the
 * rest pose; the hold law's gains (assumed, tuned on this model: with J2's reflected inertia,
 * ~0.5 kg·m² at the joint, kp 60 gives ~11 rad/s and the back-EMF, k²·n²/R ≈ 22 N·m·s/rad at
 * J2, with kd damps it well; the other joints scale with their inertia and load).
 * The power-up pose (`zero`: where the arm is parked and its counters read 0, the rest pose with
 * J1 and J5 at 0) is the plant's start and the zero a real bench's pose is counted from (the
 * bench profile's mechanics.joints zero_deg say the same).
 * X(index, gear, lo °, hi °, link J kg·m², rest rad, zero rad, kp N·m/rad, kd N·m·s/rad) */
#define YB_JOINT_TABLE(X)                                                \
    X(0, 156.0, -169.0, 169.0, 0.20, NAN, 0.0, 20.0, 2.0)                \
    X(1, 156.0, -65.0, 90.0, 0.20, YB_REST_J2, YB_REST_J2, 60.0, 4.0)    \
    X(2, 100.0, -146.0, 151.0, 0.055, YB_REST_J3, YB_REST_J3, 30.0, 2.0) \
    X(3, 71.0, -102.5, 102.5, 0.010, YB_REST_J4, YB_REST_J4, 20.0, 0.5)  \
    X(4, 71.0, -167.5, 167.5, 0.001, NAN, 0.0, 2.0, 0.1)

#define YB_JOINT_ROW(i, gear_, lo_, hi_, link_j_, rest_, zero_, kp_, kd_) \
    {gear_, lo_, hi_, link_j_, zero_},
static const struct {
    double gear, lo_deg, hi_deg, link_j, zero;
} YB_JOINT[YB_JOINTS] = {YB_JOINT_TABLE(YB_JOINT_ROW)};

static void youbot_init(void *plant)
{
    struct youbot *y = plant;
    y->supply_v = YB_SUPPLY_V;
    for (int i = 0; i < YB_JOINTS; i++) {
        struct youbot_joint *j = &y->j[i];
        j->p = YB_MOTOR;
        j->gear = YB_JOINT[i].gear;
        j->p.j = YB_MOTOR.j + YB_JOINT[i].link_j / (j->gear * j->gear);
        j->lo = YB_JOINT[i].lo_deg * DEG;
        j->hi = YB_JOINT[i].hi_deg * DEG;
    }
    /* Power-up: the rest pose, where the arm is parked (and its encoders are zeroed). */
    for (int i = 0; i < YB_JOINTS; i++) {
        y->j[i].m.angle = YB_JOINT[i].zero * y->j[i].gear;
        y->j[i].m.speed = 0.0;
    }
    y->wp = YB_MOTOR;
    y->wp.j =
        YB_MOTOR.j + 0.25 * YB_BASE_KG * YB_WHEEL_R * YB_WHEEL_R / (YB_WHEEL_GEAR * YB_WHEEL_GEAR);
    for (int i = 0; i < YB_WHEELS; i++)
        y->w[i].angle = y->w[i].speed = 0.0;
    y->x = y->y = y->theta = 0.0;
}

static void joint_angles(const struct youbot *y, double *q)
{
    for (int i = 0; i < YB_JOINTS; i++)
        q[i] = y->j[i].m.angle / y->j[i].gear;
}

static void youbot_step(void *plant, const double *duty, double dt)
{
    struct youbot *y = plant;
    double q[YB_JOINTS], tau[YB_JOINTS];
    joint_angles(y, q);
    youbot_gravity(q, tau);
    for (int i = 0; i < YB_JOINTS; i++) {
        struct youbot_joint *j = &y->j[i];
        /* Gravity as a load torque at the motor, folded into the voltage (T = K·V/R). */
        double v_load = tau[i] / j->gear * j->p.r / j->p.k;
        xrf_dc_motor_step(&j->p, &j->m, duty[i] * y->supply_v + v_load, dt);
        double lo = j->lo * j->gear, hi = j->hi * j->gear;
        if (j->m.angle > hi) {
            j->m.angle = hi;
            if (j->m.speed > 0.0)
                j->m.speed = 0.0;
        } else if (j->m.angle < lo) {
            j->m.angle = lo;
            if (j->m.speed < 0.0)
                j->m.speed = 0.0;
        }
    }
    double ws[YB_WHEELS];
    for (int i = 0; i < YB_WHEELS; i++) {
        xrf_dc_motor_step(&y->wp, &y->w[i], duty[YB_JOINTS + i] * y->supply_v, dt);
        ws[i] = y->w[i].speed / YB_WHEEL_GEAR;
    }
    /* Mecanum forward kinematics (FL, FR, RL, RR; rollers at 45° in the usual X layout). */
    double vx = YB_WHEEL_R / 4.0 * (ws[0] + ws[1] + ws[2] + ws[3]);
    double vy = YB_WHEEL_R / 4.0 * (-ws[0] + ws[1] + ws[2] - ws[3]);
    double wz = YB_WHEEL_R / (4.0 * (YB_LX + YB_LY)) * (-ws[0] + ws[1] - ws[2] + ws[3]);
    double c = cos(y->theta), s = sin(y->theta);
    y->x += (c * vx - s * vy) * dt;
    y->y += (s * vx + c * vy) * dt;
    y->theta += wz * dt;
}

static double youbot_motor_angle(const void *plant, int ch)
{
    const struct youbot *y = plant;
    if (ch >= 0 && ch < YB_JOINTS)
        return y->j[ch].m.angle;
    if (ch >= YB_JOINTS && ch < YB_CHANNELS)
        return y->w[ch - YB_JOINTS].angle;
    return NAN;
}

static int youbot_state(const void *plant, double *state, int n)
{
    const struct youbot *y = plant;
    double v[YB_JOINTS + 3];
    joint_angles(y, v);
    v[YB_JOINTS] = y->x;
    v[YB_JOINTS + 1] = y->y;
    v[YB_JOINTS + 2] = y->theta;
    int k = n < YB_JOINTS + 3 ? n : YB_JOINTS + 3;
    for (int i = 0; i < k; i++)
        state[i] = v[i];
    return k;
}

/* The snapshot the watcher takes over (plant.h): motor angle and speed of every channel, then
 * the base pose. */
#define YB_SNAPSHOT (2 * YB_CHANNELS + 3)

static int youbot_save(const void *plant, double *out, int n)
{
    const struct youbot *y = plant;
    double v[YB_SNAPSHOT];
    for (int i = 0; i < YB_JOINTS; i++) {
        v[2 * i] = y->j[i].m.angle;
        v[2 * i + 1] = y->j[i].m.speed;
    }
    for (int i = 0; i < YB_WHEELS; i++) {
        v[2 * (YB_JOINTS + i)] = y->w[i].angle;
        v[2 * (YB_JOINTS + i) + 1] = y->w[i].speed;
    }
    v[2 * YB_CHANNELS] = y->x;
    v[2 * YB_CHANNELS + 1] = y->y;
    v[2 * YB_CHANNELS + 2] = y->theta;
    int k = n < YB_SNAPSHOT ? n : YB_SNAPSHOT;
    for (int i = 0; i < k; i++)
        out[i] = v[i];
    return k;
}

/* A value from memory the student's program can write: finite and within [lo, hi], else
 * `fallback`. */
static double sane(double v, double lo, double hi, double fallback)
{
    if (!isfinite(v))
        return fallback;
    return v < lo ? lo : (v > hi ? hi : v);
}

/* Speeds beyond what the motors reach at full supply are not physical: bounded there. */
#define YB_MAX_MOTOR_SPEED 2000.0 /* rad/s */
#define YB_MAX_REACH_M 1.0e6

static void youbot_load(void *plant, const double *in, int n)
{
    struct youbot *y = plant;
    if (n < YB_SNAPSHOT)
        return; /* not a youBot snapshot: keep the init pose */
    for (int i = 0; i < YB_JOINTS; i++) {
        struct youbot_joint *j = &y->j[i];
        double lo = j->lo * j->gear, hi = j->hi * j->gear;
        j->m.angle = sane(in[2 * i], lo, hi, j->m.angle);
        j->m.speed = sane(in[2 * i + 1], -YB_MAX_MOTOR_SPEED, YB_MAX_MOTOR_SPEED, 0.0);
    }
    for (int i = 0; i < YB_WHEELS; i++) {
        /* Wheel angles only matter modulo a turn for the encoder: any finite value is kept. */
        y->w[i].angle = sane(in[2 * (YB_JOINTS + i)], -1e9, 1e9, 0.0);
        y->w[i].speed =
            sane(in[2 * (YB_JOINTS + i) + 1], -YB_MAX_MOTOR_SPEED, YB_MAX_MOTOR_SPEED, 0.0);
    }
    y->x = sane(in[2 * YB_CHANNELS], -YB_MAX_REACH_M, YB_MAX_REACH_M, 0.0);
    y->y = sane(in[2 * YB_CHANNELS + 1], -YB_MAX_REACH_M, YB_MAX_REACH_M, 0.0);
    y->theta = sane(in[2 * YB_CHANNELS + 2], -1e6, 1e6, 0.0);
}

/* The hold law's view of the arm (xrf/hold.h): the same joints, motor and gravity model. The
 * closing sequence moves at 20 °/s (a person sees it coming) after 0.5 s of holding; at rest
 * within 1° and still. */
#define YB_HOLD_JOINT(i, gear_, lo_, hi_, link_j_, rest_, zero_, kp_, kd_) \
    {.channel = i,                                                         \
     .gear = gear_,                                                        \
     .k = YB_MOTOR_K,                                                      \
     .r = YB_MOTOR_R,                                                      \
     .lo = (lo_)*DEG,                                                      \
     .hi = (hi_)*DEG,                                                      \
     .rest = rest_,                                                        \
     .zero = zero_,                                                        \
     .kp = kp_,                                                            \
     .kd = kd_,                                                            \
     .max_duty = 1.0},

static const struct xrf_hold_arm youbot_arm = {
    .joints = YB_JOINTS,
    .joint = {YB_JOINT_TABLE(YB_HOLD_JOINT)},
    .supply_v = YB_SUPPLY_V,
    .hold_s = 0.5,
    .rest_speed = 20.0 * DEG,
    .rest_push = 5.0 * DEG,
    .rest_tol = 1.0 * DEG,
    .still = 0.02,
    .max_s = 20.0,
    /* Assumed: above any speed a joint reaches, driven (the youBot's manual: ~90 °/s) or falling
     * unpowered (this model's elbow: ~3 rad/s), so a real motion is never taken for a jump; at
     * J2's 156:1 and 4096 counts the 14-bit counter is then unambiguous between samples up to
     * ~30 ms apart (watch.c samples every 2 ms). */
    .max_speed = 5.0,
    .gravity = youbot_gravity,
};

const struct xrf_plant_ops xrf_plant_youbot = {
    .name = "youbot",
    .title = "youBot-like arm (5 joints under gravity) on a mecanum base",
    .axes = YB_CHANNELS,
    .state_len = YB_JOINTS + 3,
    .state_names = "j1 rad, j2 rad, j3 rad, j4 rad, j5 rad, x m, y m, theta rad",
    .size = sizeof(struct youbot),
    .init = youbot_init,
    .step = youbot_step,
    .motor_angle = youbot_motor_angle,
    .state = youbot_state,
    .snapshot_len = YB_SNAPSHOT,
    .save = youbot_save,
    .load = youbot_load,
    .arm = &youbot_arm,
};
