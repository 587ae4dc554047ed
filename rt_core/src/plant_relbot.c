/*
 * plant_relbot.c — the RELbot: two identical wheel motors behind a 15.58:1 gearbox, the robot
 * integrated with unicycle kinematics. Gear and wheel from PLANTS.md; motor, mass and track
 * width are assumptions (simulator.md).
 *
 * The right motor is mounted mirrored: positive voltage turns its shaft (and counts its encoder)
 * the same way as the left one, but that rolls the right wheel backwards. Driving straight
 * forward therefore needs pwm1 > 0 and pwm2 < 0, and the right encoder counts down, exactly as
 * the course code expects.
 */
#include "plant.h"

#define RELBOT_MASS_KG 2.0    /* assumed: Pi, ico board, battery, frame */
#define RELBOT_WHEEL_J 1.0e-4 /* assumed: one wheel with hub, kg·m² */
#define RELBOT_MOTOR_J 1.0e-6 /* assumed rotor inertia, kg·m² */

/* Channel 1 = left wheel, channel 2 = right wheel (motor mounted mirrored). */
struct xrf_relbot {
    struct xrf_dc_motor_params p; /* same motor type on both sides */
    double gear;                  /* motor revolutions per wheel revolution */
    double wheel_radius;          /* m */
    double track;                 /* distance between the wheel contact points, m */
    double supply_v;
    struct xrf_dc_motor m[2];
    double x, y, theta; /* pose in the start frame: m, m, rad */
};

static void relbot_init(void *plant)
{
    struct xrf_relbot *r = plant;
    r->gear = 15.58;
    r->wheel_radius = 0.101 / 2.0;
    r->track = 0.20;
    r->supply_v = XRF_PLANT_SUPPLY_V;

    /* Each wheel carries half the robot's mass as if it rolled alone: rotation about the
     * vertical axis is not coupled between the wheels (simple model, see simulator.md). */
    double rr = r->wheel_radius;
    double j_wheel_side = RELBOT_WHEEL_J + 0.5 * RELBOT_MASS_KG * rr * rr;
    r->p.k = 0.02;
    r->p.r = 4.0;
    r->p.j = RELBOT_MOTOR_J + j_wheel_side / (r->gear * r->gear);
    r->p.b = 1.0e-6;
    r->p.tc = 2.0e-3;

    for (int i = 0; i < 2; i++) {
        r->m[i].angle = 0.0;
        r->m[i].speed = 0.0;
    }
    r->x = r->y = r->theta = 0.0;
}

/* Wheel speeds (rad/s) with positive meaning "this wheel rolls forward". */
static double wheel_left(const struct xrf_relbot *r)
{
    return r->m[0].speed / r->gear;
}

static double wheel_right(const struct xrf_relbot *r)
{
    return -r->m[1].speed / r->gear;
}

static void relbot_step(void *plant, const double duty[XRF_MAX_CHANNELS], double dt)
{
    struct xrf_relbot *r = plant;
    for (int i = 0; i < 2; i++)
        xrf_dc_motor_step(&r->p, &r->m[i], duty[i] * r->supply_v, dt);

    double vl = wheel_left(r) * r->wheel_radius;
    double vr = wheel_right(r) * r->wheel_radius;
    double v = 0.5 * (vl + vr);
    double omega = (vr - vl) / r->track;
    /* Heading at the middle of the step: second-order accurate on arcs at no extra cost. */
    double th_mid = r->theta + 0.5 * omega * dt;
    r->x += v * cos(th_mid) * dt;
    r->y += v * sin(th_mid) * dt;
    r->theta += omega * dt;
}

static double relbot_motor_angle(const void *plant, int ch)
{
    const struct xrf_relbot *r = plant;
    return (ch == 0 || ch == 1) ? r->m[ch].angle : NAN;
}

static int relbot_state(const void *plant, double *state, int n)
{
    const struct xrf_relbot *r = plant;
    const double v[5] = {r->x, r->y, r->theta, wheel_left(r), wheel_right(r)};
    int k = n < 5 ? n : 5;
    for (int i = 0; i < k; i++)
        state[i] = v[i];
    return k;
}

const struct xrf_plant_ops xrf_plant_relbot = {
    .name = "relbot",
    .title = "RELbot (differential drive)",
    .axes = 2,
    .state_len = 5,
    .state_names = "x m, y m, theta rad, wheel_left rad/s, wheel_right rad/s",
    .size = sizeof(struct xrf_relbot),
    .init = relbot_init,
    .step = relbot_step,
    .motor_angle = relbot_motor_angle,
    .state = relbot_state,
};
