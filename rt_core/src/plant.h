/*
 * plant.h — private to the simulated board: the DC motor model shared by both robots and the
 * Jiwy and RELbot plants. Parameter values and their sources: docs/rt_core/simulator.md.
 *
 * All plants are plain structs the board embeds, so a step never allocates.
 */
#ifndef XRF_PLANT_H
#define XRF_PLANT_H

#include <math.h>

#define XRF_PLANT_SUPPLY_V 12.0 /* default supply the PWM duty scales */

struct xrf_dc_motor_params {
    double k;  /* torque constant N·m/A == back-EMF constant V·s/rad */
    double r;  /* armature resistance, ohm */
    double j;  /* total inertia reflected to the motor shaft, kg·m² */
    double b;  /* total viscous damping reflected to the motor shaft, N·m·s/rad */
    double tc; /* Coulomb friction at the motor shaft, N·m */
};

struct xrf_dc_motor {
    double angle; /* motor shaft, rad */
    double speed; /* motor shaft, rad/s */
};

/* One step of J·dw/dt = K·(V − K·w)/R − b·w − Tc·sign(w). Armature inductance is neglected
 * (its time constant is far below the 100 us step). The linear damping (viscous + back-EMF) is
 * taken implicitly so the step is stable for any dt; Coulomb friction is then applied as an
 * impulse that may bring the shaft to rest but never reverses it, which gives true stiction:
 * a drive torque below Tc leaves a resting shaft at rest. */
static inline void xrf_dc_motor_step(const struct xrf_dc_motor_params *p, struct xrf_dc_motor *m,
                                     double volts, double dt)
{
    double drive = p->k * volts / p->r;
    double damping = p->b + p->k * p->k / p->r;
    double w = (m->speed + dt * drive / p->j) / (1.0 + dt * damping / p->j);
    double dw_friction = dt * p->tc / p->j;
    if (w > dw_friction)
        w -= dw_friction;
    else if (w < -dw_friction)
        w += dw_friction;
    else
        w = 0.0;
    m->speed = w;
    m->angle += w * dt;
}

/* Jiwy: channel 1 = pan, channel 2 = tilt. */
struct xrf_jiwy {
    struct xrf_dc_motor_params p[2];
    double ratio[2];   /* camera angle / motor angle (gearbox × belt) */
    double limit[2];   /* end stop, rad at the camera, symmetric */
    double supply_v;
    struct xrf_dc_motor m[2];
};

void xrf_jiwy_init(struct xrf_jiwy *j);
/* duty[ch] in [-1, 1] for channels 1..4 (index 0..3); channels 3, 4 are not connected. */
void xrf_jiwy_step(struct xrf_jiwy *j, const double duty[4], double dt);
/* Motor shaft angle behind encoder channel ch (0-based), or NAN when nothing is connected. */
double xrf_jiwy_motor_angle(const struct xrf_jiwy *j, int ch);
int xrf_jiwy_state(const struct xrf_jiwy *j, double *state, int n);
void xrf_jiwy_mirror(const struct xrf_jiwy *j, double plant[8]);

/* RELbot: channel 1 = left wheel, channel 2 = right wheel (motor mounted mirrored). */
struct xrf_relbot {
    struct xrf_dc_motor_params p; /* same motor type on both sides */
    double gear;         /* motor revolutions per wheel revolution */
    double wheel_radius; /* m */
    double track;        /* distance between the wheel contact points, m */
    double supply_v;
    struct xrf_dc_motor m[2];
    double x, y, theta;  /* pose in the start frame: m, m, rad */
};

void xrf_relbot_init(struct xrf_relbot *r);
void xrf_relbot_step(struct xrf_relbot *r, const double duty[4], double dt);
double xrf_relbot_motor_angle(const struct xrf_relbot *r, int ch);
int xrf_relbot_state(const struct xrf_relbot *r, double *state, int n);
void xrf_relbot_mirror(const struct xrf_relbot *r, double plant[8]);

#endif /* XRF_PLANT_H */
