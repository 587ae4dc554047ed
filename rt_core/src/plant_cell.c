/*
 * plant_cell.c — a production-cell-like machine (after the thesis's Production Cell use case,
 * USE_CASES.md): three axes, each a DC motor through a gear train or lead screw to a load moving
 * between two hard stops, with an end switch near each stop wired to the channel's two input
 * pins and a relative encoder on the motor. Nothing tells the controller where an axis is at
 * power-up: the plant starts from any pose (`start=<seed>` in the fault spec picks one), and
 * the encoders count from wherever the axes were at the board's RESET. A controller homes each
 * axis on its home switch before it may move the machine (the example does, in INITIALISING).
 *
 * Channel 1 = the rotary table (rad), 2 = the press ram (m, down positive), 3 = the feeder arm
 * (m, out positive). Pin 1 of channel n = axis n's home switch (closed within `zone` of the low
 * stop), pin 2 = its far-end switch (closed within `zone` of the high stop). Positive duty moves
 * every axis towards its high stop and counts its encoder up. Positions in state() are measured
 * from the home switch's edge (low stop + zone), the zero a homed controller finds.
 *
 * Every figure is an assumption of a small lab machine (no datasheet: docs/rt_core/simulator.md):
 * the RELbot's motor type on all three axes; the screws and loads keep their pose unpowered
 * (self-locking screws, no gravity term), as the use case says of the Production Cell.
 */
#include <stdint.h>

#include "plant.h"

#ifndef M_PI
#define M_PI 3.14159265358979323846
#endif

#define CELL_AXES 3
#define CELL_MOTOR_J 1.0e-6 /* rotor, as the RELbot's motor */

struct cell_axis {
    struct xrf_dc_motor_params p;
    double out_per_rad; /* load travel (rad or m) per motor radian */
    double lo, hi;      /* hard stops, load units */
    double zone;        /* a switch is closed within this of its stop */
    double pos;         /* load position, load units */
    struct xrf_dc_motor m;
};

struct cell {
    double supply_v;
    struct cell_axis ax[CELL_AXES];
};

/* A self-locking axis: Coulomb friction as the RELbot's gear train, light bearings. */
static void axis_init(struct cell_axis *a, double out_per_rad, double load_j_at_motor, double lo,
                      double hi, double zone)
{
    a->p.k = 0.02;
    a->p.r = 4.0;
    a->p.j = CELL_MOTOR_J + load_j_at_motor;
    a->p.b = 2.0e-6;
    a->p.tc = 2.0e-3;
    a->out_per_rad = out_per_rad;
    a->lo = lo;
    a->hi = hi;
    a->zone = zone;
    a->pos = 0.5 * (lo + hi); /* the default start: mid-travel */
    a->m.angle = a->pos / out_per_rad;
    a->m.speed = 0.0;
}

static void cell_init(void *plant)
{
    struct cell *c = plant;
    c->supply_v = XRF_PLANT_SUPPLY_V;
    /* Rotary table: 50:1 worm gear, a 0.02 kg·m² table (reflected /50²), 270° of travel. */
    const double g = 50.0;
    axis_init(&c->ax[0], 1.0 / g, 0.02 / (g * g), 0.0, 1.5 * M_PI, 0.10);
    /* Press ram: 4 mm lead screw, a 2 kg ram (m·(lead/2π)² at the motor), 150 mm of stroke. */
    const double press = 0.004 / (2.0 * M_PI);
    axis_init(&c->ax[1], press, 2.0e-6 + 2.0 * press * press, 0.0, 0.150, 0.005);
    /* Feeder arm: 8 mm lead screw, a 1 kg carriage, 200 mm of travel. */
    const double feed = 0.008 / (2.0 * M_PI);
    axis_init(&c->ax[2], feed, 1.0e-6 + 1.0 * feed * feed, 0.0, 0.200, 0.005);
}

/* xorshift32: the same seed gives the same start pose, so a failing seed can be replayed. */
static uint32_t next_rand(uint32_t *s)
{
    uint32_t x = *s;
    x ^= x << 13;
    x ^= x >> 17;
    x ^= x << 5;
    return *s = x;
}

static void cell_start(void *plant, uint32_t seed)
{
    struct cell *c = plant;
    uint32_t s = seed ? seed * 2654435761u : 1u;
    if (!s)
        s = 1u;
    for (int i = 0; i < CELL_AXES; i++) {
        struct cell_axis *a = &c->ax[i];
        double u = (double)(next_rand(&s) >> 8) / (double)(1u << 24); /* [0, 1) */
        a->pos = a->lo + u * (a->hi - a->lo);
        a->m.angle = a->pos / a->out_per_rad;
        a->m.speed = 0.0;
    }
}

static void cell_step(void *plant, const double duty[XRF_MAX_CHANNELS], double dt)
{
    struct cell *c = plant;
    for (int i = 0; i < CELL_AXES; i++) {
        struct cell_axis *a = &c->ax[i];
        xrf_dc_motor_step(&a->p, &a->m, duty[i] * c->supply_v, dt);
        /* Hard stops, as on the stage: only motion into the stop is killed. */
        double lo = a->lo / a->out_per_rad, hi = a->hi / a->out_per_rad;
        if (a->m.angle > hi) {
            a->m.angle = hi;
            if (a->m.speed > 0.0)
                a->m.speed = 0.0;
        } else if (a->m.angle < lo) {
            a->m.angle = lo;
            if (a->m.speed < 0.0)
                a->m.speed = 0.0;
        }
        a->pos = a->m.angle * a->out_per_rad;
    }
}

static double cell_motor_angle(const void *plant, int ch)
{
    const struct cell *c = plant;
    return (ch >= 0 && ch < CELL_AXES) ? c->ax[ch].m.angle : NAN;
}

static unsigned cell_inputs(const void *plant)
{
    const struct cell *c = plant;
    unsigned pins = 0;
    for (int i = 0; i < CELL_AXES; i++) {
        const struct cell_axis *a = &c->ax[i];
        if (a->pos <= a->lo + a->zone)
            pins |= 1u << (2 * i);
        if (a->pos >= a->hi - a->zone)
            pins |= 1u << (2 * i + 1);
    }
    return pins;
}

static int cell_state(const void *plant, double *state, int n)
{
    const struct cell *c = plant;
    double v[2 * CELL_AXES];
    for (int i = 0; i < CELL_AXES; i++) {
        const struct cell_axis *a = &c->ax[i];
        v[i] = a->pos - (a->lo + a->zone);
        v[CELL_AXES + i] = a->m.speed * a->out_per_rad;
    }
    int k = n < 2 * CELL_AXES ? n : 2 * CELL_AXES;
    for (int i = 0; i < k; i++)
        state[i] = v[i];
    return k;
}

const struct xrf_plant_ops xrf_plant_cell = {
    .name = "cell",
    .title = "Production cell (rotary table, press, feeder; homing switches)",
    .axes = CELL_AXES,
    .state_len = 2 * CELL_AXES,
    .state_names = "table rad, press m, feeder m, table rad/s, press m/s, feeder m/s",
    .size = sizeof(struct cell),
    .init = cell_init,
    .step = cell_step,
    .motor_angle = cell_motor_angle,
    .state = cell_state,
    .inputs = cell_inputs,
    .start = cell_start,
};
