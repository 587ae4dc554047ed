/*
 * plant_stage.c — a one-axis linear stage: one DC motor turning a lead screw directly (no
 * gearbox) that moves a carriage between two hard end stops. The design's third robot
 * (DESIGN.md); PLANTS.md has no figures for it, so every figure here is an assumption of a small
 * lab stage (simulator.md): the RELbot's motor type, an 8 mm lead screw, a 0.5 kg carriage,
 * 200 mm of travel centred on where the carriage starts.
 *
 * Channel 1 = the motor; positive duty moves the carriage towards +x and counts the encoder up.
 */
#include "plant.h"

#ifndef M_PI
#define M_PI 3.14159265358979323846
#endif

#define STAGE_LEAD_M 0.008        /* carriage travel per screw (= motor) revolution */
#define STAGE_HALF_TRAVEL_M 0.100 /* end stops at +-100 mm from the start position */
#define STAGE_CARRIAGE_KG 0.5
#define STAGE_SCREW_J 1.0e-6 /* screw and coupling, kg·m² */
#define STAGE_MOTOR_J 1.0e-6 /* rotor, as the RELbot's motor */

struct stage {
    struct xrf_dc_motor_params p;
    double m_per_rad; /* carriage metres per motor radian */
    double limit;     /* end stop, m from the middle, symmetric */
    double supply_v;
    struct xrf_dc_motor m;
};

static void stage_init(void *plant)
{
    struct stage *s = plant;
    s->m_per_rad = STAGE_LEAD_M / (2.0 * M_PI);
    s->limit = STAGE_HALF_TRAVEL_M;
    s->supply_v = XRF_PLANT_SUPPLY_V;
    /* The carriage's mass reaches the motor through the screw as m·(lead/2π)². */
    s->p.k = 0.02;
    s->p.r = 4.0;
    s->p.j = STAGE_MOTOR_J + STAGE_SCREW_J + STAGE_CARRIAGE_KG * s->m_per_rad * s->m_per_rad;
    s->p.b = 2.0e-6;  /* motor and screw bearings */
    s->p.tc = 2.0e-3; /* nut and guide friction, as the RELbot's gear train */
    s->m.angle = 0.0;
    s->m.speed = 0.0;
}

static void stage_step(void *plant, const double duty[XRF_MAX_CHANNELS], double dt)
{
    struct stage *s = plant;
    xrf_dc_motor_step(&s->p, &s->m, duty[0] * s->supply_v, dt);
    /* A hard stop, as on the Jiwy: only motion into the stop is killed. */
    double max_motor = s->limit / s->m_per_rad;
    if (s->m.angle > max_motor) {
        s->m.angle = max_motor;
        if (s->m.speed > 0.0)
            s->m.speed = 0.0;
    } else if (s->m.angle < -max_motor) {
        s->m.angle = -max_motor;
        if (s->m.speed < 0.0)
            s->m.speed = 0.0;
    }
}

static double stage_motor_angle(const void *plant, int ch)
{
    const struct stage *s = plant;
    return ch == 0 ? s->m.angle : NAN;
}

static int stage_state(const void *plant, double *state, int n)
{
    const struct stage *s = plant;
    const double v[2] = {s->m.angle * s->m_per_rad, s->m.speed * s->m_per_rad};
    int k = n < 2 ? n : 2;
    for (int i = 0; i < k; i++)
        state[i] = v[i];
    return k;
}

const struct xrf_plant_ops xrf_plant_stage = {
    .name = "stage",
    .title = "Linear stage (one axis, lead screw)",
    .axes = 1,
    .state_len = 2,
    .state_names = "position m, velocity m/s",
    .size = sizeof(struct stage),
    .init = stage_init,
    .step = stage_step,
    .motor_angle = stage_motor_angle,
    .state = stage_state,
};
