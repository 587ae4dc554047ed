/*
 * xrf/hold.h — the `hold` safe reaction's fallback law (XRF_SAFE_REACTIONS in xrf/watch.h): what
 * the safety watcher runs, off the appliance's Python and off the student's program, when a
 * gravity-loaded arm loses its controller. One C implementation for the simulated board (the
 * watcher steps the plant itself once the loop is gone) and a real board (the same law over
 * spidev, the duty in xrf/ico.h frames): it only sees measured joint angles and gives duties.
 *
 *   1. HOLD: hold the pose measured at the fault, with gravity compensation (the arm's model)
 *      and damping, for hold_s seconds, so a transient fault never moves the arm at all;
 *   2. CLOSING: move the reference from that pose to the rest pose at a bounded joint speed
 *      (rest_speed rad/s): the closing sequence a STOPPING state would have done;
 *   3. REST: once every joint is within rest_tol of its rest pose and still (or after max_s,
 *      whatever the arm did), every output zero.
 *      The rest pose leans each gravity-loaded joint on a hard stop (the arm model says so), so
 *      zero there drops nothing.
 *
 * Everything here is fixed-size and allocation-free: xrf_hold_step runs in the watcher's 1 kHz
 * tick and makes no system call.
 */
#ifndef XRF_HOLD_H
#define XRF_HOLD_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define XRF_HOLD_JOINTS_MAX 8

/* A joint the law drives: the board channel (0-based) behind it and the motor + gear figures
 * the law needs to turn a joint torque into a duty. */
struct xrf_hold_joint {
    int channel;     /* 0-based board channel: PWM and encoder */
    double gear;     /* joint angle = motor angle / gear */
    double k;        /* motor torque constant N·m/A */
    double r;        /* armature resistance, ohm */
    double lo, hi;   /* joint limits, rad (the hard stops) */
    double rest;     /* rest pose, rad; NAN: the joint stays where it was held */
    double zero;     /* the joint's angle where its counter reads 0: the pose the arm is parked
                      * in when a run starts (a real bench's pose = zero + counts / scale) */
    double kp, kd;   /* joint-side stiffness N·m/rad and damping N·m·s/rad */
    double max_duty; /* |duty| bound, 0..1 */
};

/* An arm as the law sees it: its joints and its gravity model. */
struct xrf_hold_arm {
    int joints;
    struct xrf_hold_joint joint[XRF_HOLD_JOINTS_MAX];
    double supply_v;   /* what duty 1 is, volts */
    double hold_s;     /* HOLD phase before the closing sequence starts */
    double rest_speed; /* closing sequence: largest joint speed of the reference, rad/s */
    double rest_push;  /* rad the reference goes past a rest pose on a hard stop (presses it on) */
    double rest_tol;   /* rad: at rest within this of the rest pose ... */
    double still;      /* ... and slower than this, rad/s */
    double max_s;      /* the whole sequence's bound: REST (outputs zero) after this at most */
    double max_speed;  /* rad/s no joint can exceed: a faster count is not the arm (a reset,
                        * garbage), and what the encoders must be sampled often enough for */
    /* Joint-side gravity torque at pose q (the torque gravity puts on each joint, positive
     * in the joint's positive direction). */
    void (*gravity)(const double *q, double *tau);
};

#define XRF_HOLD_PHASE_HOLD 1
#define XRF_HOLD_PHASE_CLOSING 2
#define XRF_HOLD_PHASE_REST 3

struct xrf_hold {
    const struct xrf_hold_arm *arm;
    int phase;
    double t;                           /* since the fault, s */
    double q_held[XRF_HOLD_JOINTS_MAX]; /* the pose measured at the fault */
    double q_ref[XRF_HOLD_JOINTS_MAX];  /* the reference now */
    double qd_ref[XRF_HOLD_JOINTS_MAX]; /* its speed, rad/s */
    double q_last[XRF_HOLD_JOINTS_MAX]; /* the previous measurement (speed by difference) */
    double qd[XRF_HOLD_JOINTS_MAX];     /* filtered measured speed, rad/s */
    double drop_max; /* largest drop so far, rad: a joint past its reference the way gravity
                      * pulls it (xrf_hold_step) */
    double rest_t;   /* t at which REST was reached; < 0 before */
};

/* Start the law at the measured pose q (arm->joints angles, rad). A non-finite angle or one
 * outside the joint's limits is clamped into them (q may come from memory the student's
 * program could write). */
void xrf_hold_begin(struct xrf_hold *h, const struct xrf_hold_arm *arm, const double *q);
/* One tick of dt seconds with the measured pose q: the duty of each joint's channel into
 * duty[channel] (channels the arm does not drive are left as they are). Returns the phase. */
int xrf_hold_step(struct xrf_hold *h, const double *q, double dt, double *duty);

#ifdef __cplusplus
}
#endif

#endif /* XRF_HOLD_H */
