/*
 * plant_jiwy.c — the Jiwy pan-tilt camera: two DC motors driving the camera through a 1:19
 * gearbox and a belt (pan 1:1, tilt 1:4), with hard end stops. Figures from PLANTS.md (a 20-sim
 * model of the Jiwy); the electrical side and the stops are our assumptions (simulator.md).
 */
#include <math.h>

#include "plant.h"

#ifndef M_PI
#define M_PI 3.14159265358979323846
#endif

#define DEG (M_PI / 180.0)

/* Channel 1 = pan, channel 2 = tilt. */
struct xrf_jiwy {
    struct xrf_dc_motor_params p[2];
    double ratio[2]; /* camera angle / motor angle (gearbox × belt) */
    double limit[2]; /* end stop, rad at the camera, symmetric */
    double supply_v;
    struct xrf_dc_motor m[2];
};

/* Per axis: motor figures, camera-side figures, transmission, assumed electrical side. */
struct axis_figures {
    double k, j_motor, b_motor, gearbox, belt, j_camera, b_camera, r, tc, stop_deg;
};

static const struct axis_figures figures[2] = {
    /* pan */
    {.k = 0.018,
     .j_motor = 2.06e-7,
     .b_motor = 1.77e-6,
     .gearbox = 1.0 / 19.0,
     .belt = 1.0,
     .j_camera = 3.0e-4,
     .b_camera = 2.0e-4,
     .r = 2.5,
     .tc = 1.0e-3,
     .stop_deg = 90.0},
    /* tilt */
    {.k = 0.00701,
     .j_motor = 5.28e-8,
     .b_motor = 4.0e-7,
     .gearbox = 1.0 / 19.0,
     .belt = 0.25,
     .j_camera = 4.5e-5,
     .b_camera = 1.0e-4,
     .r = 4.0,
     .tc = 2.0e-4,
     .stop_deg = 45.0},
};

static void jiwy_init(void *plant)
{
    struct xrf_jiwy *j = plant;
    for (int a = 0; a < 2; a++) {
        const struct axis_figures *f = &figures[a];
        double n = f->gearbox * f->belt;
        /* The camera side reaches the motor scaled by the square of the ratio. */
        j->p[a].k = f->k;
        j->p[a].r = f->r;
        j->p[a].j = f->j_motor + f->j_camera * n * n;
        j->p[a].b = f->b_motor + f->b_camera * n * n;
        j->p[a].tc = f->tc;
        j->ratio[a] = n;
        j->limit[a] = f->stop_deg * DEG;
        j->m[a].angle = 0.0;
        j->m[a].speed = 0.0;
    }
    j->supply_v = XRF_PLANT_SUPPLY_V;
}

static void jiwy_step(void *plant, const double duty[XRF_MAX_CHANNELS], double dt)
{
    struct xrf_jiwy *j = plant;
    for (int a = 0; a < 2; a++) {
        struct xrf_dc_motor *m = &j->m[a];
        xrf_dc_motor_step(&j->p[a], m, duty[a] * j->supply_v, dt);
        /* A hard stop: the gearing is rigid, so stopping the camera stops the motor; only
         * motion into the stop is killed, so the axis can drive away from it at once. */
        double max_motor = j->limit[a] / j->ratio[a];
        if (m->angle > max_motor) {
            m->angle = max_motor;
            if (m->speed > 0.0)
                m->speed = 0.0;
        } else if (m->angle < -max_motor) {
            m->angle = -max_motor;
            if (m->speed < 0.0)
                m->speed = 0.0;
        }
    }
}

static double jiwy_motor_angle(const void *plant, int ch)
{
    const struct xrf_jiwy *j = plant;
    return (ch == 0 || ch == 1) ? j->m[ch].angle : NAN;
}

static int jiwy_state(const void *plant, double *state, int n)
{
    const struct xrf_jiwy *j = plant;
    const double v[4] = {
        j->m[0].angle * j->ratio[0],
        j->m[1].angle * j->ratio[1],
        j->m[0].speed * j->ratio[0],
        j->m[1].speed * j->ratio[1],
    };
    int k = n < 4 ? n : 4;
    for (int i = 0; i < k; i++)
        state[i] = v[i];
    return k;
}

const struct xrf_plant_ops xrf_plant_jiwy = {
    .name = "jiwy",
    .title = "Jiwy (pan-tilt camera)",
    .axes = 2,
    .state_len = 4,
    .state_names = "pan rad, tilt rad, pan_rate rad/s, tilt_rate rad/s",
    .size = sizeof(struct xrf_jiwy),
    .init = jiwy_init,
    .step = jiwy_step,
    .motor_angle = jiwy_motor_angle,
    .state = jiwy_state,
};
