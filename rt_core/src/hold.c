/*
 * hold.c — the `hold` safe reaction's law (xrf/hold.h): gravity compensation + PD on a
 * reference that first stays at the pose measured at the fault, then moves to the rest pose at a
 * bounded speed; zero outputs once at rest. Used by the watcher (watch.c) for the simulated
 * board and a real one alike; the C unit test drives it on the youBot plant.
 */
#include "xrf/hold.h"

#include <math.h>
#include <string.h>

/* The measured speed is a difference of encoder angles: filtered over a few ticks so encoder
 * quantisation does not turn into duty noise, short enough to damp the arm's ~10 rad/s mode. */
#define HOLD_SPEED_FILTER_S 0.003

static double clamp(double x, double lo, double hi)
{
    return x < lo ? lo : (x > hi ? hi : x);
}

/* A measurement as the law uses it: finite and inside the joint's travel (plus a little, so a
 * joint pressed on its stop still reads as there). */
static double sane_angle(const struct xrf_hold_joint *j, double q, double fallback)
{
    if (!isfinite(q))
        q = fallback;
    return clamp(q, j->lo - 0.1, j->hi + 0.1);
}

void xrf_hold_begin(struct xrf_hold *h, const struct xrf_hold_arm *arm, const double *q)
{
    memset(h, 0, sizeof *h);
    h->arm = arm;
    h->phase = XRF_HOLD_PHASE_HOLD;
    h->rest_t = -1.0;
    for (int i = 0; i < arm->joints && i < XRF_HOLD_JOINTS_MAX; i++) {
        const struct xrf_hold_joint *j = &arm->joint[i];
        double a = q[i];
        if (!isfinite(a))
            a = isfinite(j->rest) ? j->rest : 0.5 * (j->lo + j->hi);
        a = clamp(a, j->lo, j->hi);
        h->q_held[i] = h->q_ref[i] = h->q_last[i] = a;
    }
}

int xrf_hold_step(struct xrf_hold *h, const double *q_in, double dt, double *duty)
{
    const struct xrf_hold_arm *arm = h->arm;
    int n = arm->joints < XRF_HOLD_JOINTS_MAX ? arm->joints : XRF_HOLD_JOINTS_MAX;
    if (!(dt > 0.0) || dt > 0.1)
        dt = 0.001; /* a stalled tick must not make the speed estimate jump */
    h->t += dt;
    double q[XRF_HOLD_JOINTS_MAX] = {0};
    double alpha = dt / (dt + HOLD_SPEED_FILTER_S);
    for (int i = 0; i < n; i++) {
        q[i] = sane_angle(&arm->joint[i], q_in[i], h->q_last[i]);
        h->qd[i] += alpha * ((q[i] - h->q_last[i]) / dt - h->qd[i]);
        h->q_last[i] = q[i];
    }

    if (h->phase == XRF_HOLD_PHASE_HOLD && h->t >= arm->hold_s)
        h->phase = XRF_HOLD_PHASE_CLOSING;
    if (h->phase == XRF_HOLD_PHASE_CLOSING) {
        int arrived = 1;
        double step = arm->rest_speed * dt;
        for (int i = 0; i < n; i++) {
            const struct xrf_hold_joint *j = &arm->joint[i];
            double rest = isfinite(j->rest) ? j->rest : h->q_held[i];
            /* A rest pose on a stop: the reference goes on past it, so the arm is pressed onto
             * the stop (the gear's friction cannot leave it short), never beyond it. */
            double target = rest;
            if (isfinite(j->rest) && j->rest <= j->lo)
                target = rest - arm->rest_push;
            else if (isfinite(j->rest) && j->rest >= j->hi)
                target = rest + arm->rest_push;
            double move = clamp(target - h->q_ref[i], -step, step);
            h->q_ref[i] += move;
            h->qd_ref[i] = move / dt;
            if (fabs(rest - q[i]) > arm->rest_tol || fabs(h->qd[i]) > arm->still)
                arrived = 0;
        }
        if (arrived || h->t >= arm->max_s) {
            h->phase = XRF_HOLD_PHASE_REST;
            h->rest_t = h->t;
        }
    }
    if (h->phase == XRF_HOLD_PHASE_REST) {
        for (int i = 0; i < n; i++)
            duty[arm->joint[i].channel] = 0.0;
        return h->phase;
    }

    double tau_g[XRF_HOLD_JOINTS_MAX] = {0};
    arm->gravity(q, tau_g);
    for (int i = 0; i < n; i++) {
        /* A drop: the joint off its reference (as far as the joint can follow it, not the
         * push past a stop) in the direction gravity pulls it: sagging while held, lagging
         * behind a reference that lifts, running ahead of one that lowers. Moving the other
         * way is not a drop; for joints gravity does not load either way counts. */
        const struct xrf_hold_joint *j = &arm->joint[i];
        double e = q[i] - clamp(h->q_ref[i], j->lo, j->hi);
        double d = tau_g[i] > 0.0 ? e : (tau_g[i] < 0.0 ? -e : fabs(e));
        if (d > h->drop_max)
            h->drop_max = d;
    }
    for (int i = 0; i < n; i++) {
        const struct xrf_hold_joint *j = &arm->joint[i];
        /* The motor cancels gravity and pulls towards the reference; the armature's back-EMF
         * (not compensated) adds its own damping. */
        double tau = -tau_g[i] + j->kp * (h->q_ref[i] - q[i]) + j->kd * (h->qd_ref[i] - h->qd[i]);
        /* The reference's own speed is fed forward through the back-EMF it meets, so the
         * closing sequence does not lag behind its reference. */
        double volts = tau / j->gear * j->r / j->k + j->k * j->gear * h->qd_ref[i];
        duty[j->channel] = clamp(volts / arm->supply_v, -j->max_duty, j->max_duty);
    }
    return h->phase;
}
