/*
 * plant.h — private to the simulated board: the DC motor model every plant uses and the plant
 * operations a plant file (plant_<name>.c) fills in for its row of the plant table (plants.c).
 * Parameter values and their sources: docs/rt_core/simulator.md.
 *
 * A plant's state is a plain struct the board allocates once at open, so a step never allocates.
 */
#ifndef XRF_PLANT_H
#define XRF_PLANT_H

#include <math.h>
#include <stddef.h>
#include <stdint.h>

#include "xrf/hold.h"

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

/* One simulated plant: one row of the plant table (plants.c), defined in its own plant_<name>.c.
 * The board allocates `size` zeroed bytes for the plant's own struct at open and hands them to
 * every function here; step, motor_angle and state run in the loop's transfer, so they must not
 * allocate, lock, print or make a system call. */
struct xrf_plant_ops {
    const char *name;  /* XRF_SIM=<name>, the bench profile and example of the same name */
    const char *title; /* for people */
    int axes;          /* motor channels wired, 1..axes: PWM n drives the motor behind encoder n */
    int state_len;     /* values state() gives (<= 8, the shared-memory mirror's size) */
    const char *state_names; /* "name unit, ..." in state() order */
    size_t size;             /* of the plant's struct */
    void (*init)(void *plant);
    /* duty[ch] in [-1, 1] for channels 1..4 (index 0..3); channels beyond `axes` are ignored. */
    void (*step)(void *plant, const double duty[4], double dt);
    /* Motor shaft angle (rad) behind encoder channel ch (0-based), or NAN when nothing is
     * connected: the encoder wiring. */
    double (*motor_angle)(const void *plant, int ch);
    /* Up to n state values into state; returns how many. */
    int (*state)(const void *plant, double *state, int n);
    /* Optional (NULL: nothing wired). The plant's switches on the board's input pins: bit k =
     * pin k (0..7 in xrf_ico_in.din order: pin 1 of channel 1, pin 2 of channel 1, ...). */
    unsigned (*inputs)(const void *plant);
    /* Optional (NULL: the plant always starts from init's pose). Called after init when the
     * fault spec says `start=<seed>` (seed > 0): a start pose drawn from the seed, for plants a
     * controller must home (it starts from any pose; the same seed, the same pose). */
    void (*start)(void *plant, uint32_t seed);
    /* Optional (0/NULL: the plant has no `hold` safe reaction). The watcher keeps stepping the
     * plant once the loop process is gone (xrf/watch.h): the board writes the plant's dynamic
     * state (save: up to n values, returns how many; snapshot_len of them) to the shared
     * memory each transfer, the watcher loads it into its own copy of the plant. `load` reads
     * values the student's program could have written: it keeps every one finite and inside
     * the plant's physics (joint limits, bounded speeds), whatever it is given. `arm` is the
     * model the hold law (xrf/hold.h) drives. */
    int snapshot_len;
    int (*save)(const void *plant, double *out, int n);
    void (*load)(void *plant, const double *in, int n);
    const struct xrf_hold_arm *arm;
};

/* The plant table (plants.c): row `id` (from 1), or NULL. */
const struct xrf_plant_ops *xrf_plant_ops(int id);

#endif /* XRF_PLANT_H */
