/* The youBot-like plant and the `hold` safe reaction's law (xrf/hold.h) on it, in plain C: the
 * arm falls unpowered, the law holds it where it was and lowers it to its rest pose on the
 * stops, a hostile snapshot loads as a physical state, the mecanum base's odometry. Figures are
 * printed (the bound each is checked against is the fault tests' one, docs/developers/safety.md). */
#define _POSIX_C_SOURCE 200809L

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "../src/plant.h"
#include "xrf/hold.h"
#include "xrf/channels.h"
#include "xrf/plants.h"

#define CHECK_NAME "test_hold"
#include "check.h"

#ifndef M_PI
#define M_PI 3.14159265358979323846
#endif
#define DEG (M_PI / 180.0)

/* The largest joint drop the fault tests allow (docs/developers/safety.md says why 2°). */
#define DROP_BOUND (2.0 * DEG)
#define SUB 10 /* plant sub-steps of 100 us per 1 ms tick, as the board and the watcher */

static const struct xrf_plant_ops *ops;
static _Alignas(max_align_t) unsigned char mem[4096];

static void *fresh(void)
{
    CHECK(ops->size <= sizeof mem);
    memset(mem, 0, sizeof mem);
    ops->init(mem);
    return mem;
}

static void angles(const void *p, double *q)
{
    const struct xrf_hold_arm *arm = ops->arm;
    for (int i = 0; i < arm->joints; i++)
        q[i] = ops->motor_angle(p, arm->joint[i].channel) / arm->joint[i].gear;
}

/* A working pose: shoulder forward, elbow bent, wrist level-ish (gravity on every pitch joint). */
static void put_pose(void *p, const double *q)
{
    double snap[XRF_SIM_SNAPSHOT_MAX] = {0};
    int n = ops->save(p, snap, XRF_SIM_SNAPSHOT_MAX);
    CHECK(n == ops->snapshot_len);
    for (int i = 0; i < ops->arm->joints; i++) {
        snap[2 * i] = q[i] * ops->arm->joint[i].gear;
        snap[2 * i + 1] = 0.0;
    }
    ops->load(p, snap, n);
}

static void test_rest_pose_leans_on_the_stops(void)
{
    const struct xrf_hold_arm *arm = ops->arm;
    double q[XRF_HOLD_JOINTS_MAX], tau[XRF_HOLD_JOINTS_MAX];
    void *p = fresh();
    angles(p, q);
    /* The plant powers up in the rest pose. */
    for (int i = 1; i <= 3; i++)
        CHECK(fabs(q[i] - arm->joint[i].rest) < 1e-9);
    arm->gravity(q, tau);
    /* Gravity pushes every pitch joint into the stop it rests on. */
    CHECK(fabs(q[1] - arm->joint[1].lo) < 1e-9 && tau[1] < 0.0);
    CHECK(fabs(q[2] - arm->joint[2].hi) < 1e-9 && tau[2] > 0.0);
    CHECK(fabs(q[3] - arm->joint[3].lo) < 1e-9 && tau[3] < 0.0);
    /* And unpowered it stays there. */
    double duty[12] = {0};
    for (int k = 0; k < 1000 * SUB; k++)
        ops->step(p, duty, 1e-4);
    double q1[XRF_HOLD_JOINTS_MAX];
    angles(p, q1);
    for (int i = 0; i < arm->joints; i++)
        CHECK(fabs(q1[i] - q[i]) < 1e-6);
}

static const double WORK[5] = {0.3, 30.0 * DEG, 60.0 * DEG, 30.0 * DEG, 0.5};

static void test_unpowered_the_arm_falls(void)
{
    void *p = fresh();
    put_pose(p, WORK);
    double duty[12] = {0};
    for (int k = 0; k < 1000 * SUB; k++) /* one second */
        ops->step(p, duty, 1e-4);
    double q[XRF_HOLD_JOINTS_MAX];
    angles(p, q);
    double drop = q[1] - WORK[1];
    printf("unpowered for 1 s from the working pose: J2 fell %.1f°, J3 %.1f°, J4 %.1f°\n",
           drop / DEG, (q[2] - WORK[2]) / DEG, (q[3] - WORK[3]) / DEG);
    CHECK(drop > 5.0 * DEG);            /* forward, under gravity: what `zero` does to this arm */
    CHECK(fabs(q[0] - WORK[0]) < 1e-6); /* J1 yaw carries no gravity */
}

static void test_hold_then_rest(void)
{
    const struct xrf_hold_arm *arm = ops->arm;
    void *p = fresh();
    put_pose(p, WORK);
    double q[XRF_HOLD_JOINTS_MAX];
    angles(p, q);
    struct xrf_hold h;
    xrf_hold_begin(&h, arm, q);
    double duty[12] = {0};
    double hold_dev = 0.0, span_dev = 0.0;
    int phase = XRF_HOLD_PHASE_HOLD, ticks = 0;
    while (phase != XRF_HOLD_PHASE_REST && ticks < 30000) {
        phase = xrf_hold_step(&h, q, 0.001, duty);
        for (int k = 0; k < SUB; k++)
            ops->step(p, duty, 1e-4);
        angles(p, q);
        ticks++;
        for (int i = 0; i < arm->joints; i++) {
            if (h.t < arm->hold_s) {
                hold_dev = fmax(hold_dev, fabs(q[i] - WORK[i]));
            } else {
                /* Closing: never outside the span from the held pose to the rest pose. */
                double rest = isfinite(arm->joint[i].rest) ? arm->joint[i].rest : WORK[i];
                double lo = fmin(rest, WORK[i]), hi = fmax(rest, WORK[i]);
                span_dev = fmax(span_dev, fmax(lo - q[i], q[i] - hi));
            }
        }
    }
    printf("hold: largest deviation while holding %.3f°, outside the closing span %.3f°, drop "
           "%.3f°, at rest after %.2f s\n",
           hold_dev / DEG, span_dev / DEG, h.drop_max / DEG, h.rest_t);
    CHECK(phase == XRF_HOLD_PHASE_REST);
    CHECK(h.rest_t < arm->max_s); /* came to rest on its own, not by the time bound */
    CHECK(hold_dev < DROP_BOUND);
    CHECK(span_dev < DROP_BOUND);
    CHECK(h.drop_max < DROP_BOUND);
    for (int i = 0; i < 12; i++)
        CHECK(duty[i] == 0.0);
    /* At rest: the pitch joints on their stops, the others where they were held. */
    CHECK(fabs(q[1] - arm->joint[1].rest) < arm->rest_tol);
    CHECK(fabs(q[2] - arm->joint[2].rest) < arm->rest_tol);
    CHECK(fabs(q[3] - arm->joint[3].rest) < arm->rest_tol);
    CHECK(fabs(q[0] - WORK[0]) < DROP_BOUND && fabs(q[4] - WORK[4]) < DROP_BOUND);
    /* And zero there for two more seconds moves nothing. */
    double q_rest[XRF_HOLD_JOINTS_MAX];
    memcpy(q_rest, q, sizeof q);
    for (int k = 0; k < 2000 * SUB; k++)
        ops->step(p, duty, 1e-4);
    angles(p, q);
    for (int i = 0; i < arm->joints; i++)
        CHECK(fabs(q[i] - q_rest[i]) < 0.01 * DEG);
}

/* The law's own inputs may come from memory a student's program wrote. */
static void test_hold_takes_hostile_measurements(void)
{
    const struct xrf_hold_arm *arm = ops->arm;
    double q[XRF_HOLD_JOINTS_MAX] = {NAN, INFINITY, -1e300, 1e300, NAN};
    struct xrf_hold h;
    xrf_hold_begin(&h, arm, q);
    double duty[12] = {0};
    for (int k = 0; k < 100; k++) {
        xrf_hold_step(&h, q, k % 2 ? NAN : -5.0, duty);
        for (int i = 0; i < 12; i++)
            CHECK(isfinite(duty[i]) && fabs(duty[i]) <= 1.0);
    }
    for (int i = 0; i < arm->joints; i++)
        CHECK(h.q_held[i] >= arm->joint[i].lo && h.q_held[i] <= arm->joint[i].hi);
}

static void test_hostile_snapshot_loads_physical(void)
{
    void *p = fresh();
    double snap[XRF_SIM_SNAPSHOT_MAX];
    for (int i = 0; i < XRF_SIM_SNAPSHOT_MAX; i++)
        snap[i] = (i % 3 == 0) ? NAN : (i % 3 == 1 ? 1e308 : -INFINITY);
    ops->load(p, snap, ops->snapshot_len);
    double q[XRF_HOLD_JOINTS_MAX];
    angles(p, q);
    for (int i = 0; i < ops->arm->joints; i++)
        CHECK(isfinite(q[i]) && q[i] >= ops->arm->joint[i].lo - 1e-9 &&
              q[i] <= ops->arm->joint[i].hi + 1e-9);
    double st[8];
    int n = ops->state(p, st, 8);
    CHECK(n == 8);
    for (int i = 0; i < n; i++)
        CHECK(isfinite(st[i]));
    /* A short snapshot is not this plant's: ignored. */
    p = fresh();
    ops->load(p, snap, 3);
    angles(p, q);
    CHECK(fabs(q[1] - ops->arm->joint[1].rest) < 1e-9);
    /* Stepping on from the sanitised state stays finite. */
    p = fresh();
    ops->load(p, snap, ops->snapshot_len);
    double duty[12] = {1, -1, 1, -1, 1, 1, 1, 1, 1, 0, 0, 0};
    for (int k = 0; k < 5000; k++)
        ops->step(p, duty, 1e-4);
    n = ops->state(p, st, 8);
    for (int i = 0; i < n; i++)
        CHECK(isfinite(st[i]));
}

static void drive_base(void *p, const double w[4], double seconds, double *st)
{
    double duty[12] = {0};
    for (int i = 0; i < 4; i++)
        duty[5 + i] = w[i];
    for (int k = 0; k < (int)(seconds * 1e4); k++)
        ops->step(p, duty, 1e-4);
    ops->state(p, st, 8);
}

static void test_mecanum_odometry(void)
{
    double st[8];
    const double fwd[4] = {0.3, 0.3, 0.3, 0.3}, strafe[4] = {-0.3, 0.3, 0.3, -0.3},
                 turn[4] = {-0.3, 0.3, -0.3, 0.3};
    drive_base(fresh(), fwd, 1.0, st);
    CHECK(st[5] > 0.1 && fabs(st[6]) < 1e-9 && fabs(st[7]) < 1e-9);
    drive_base(fresh(), strafe, 1.0, st);
    CHECK(st[6] > 0.1 && fabs(st[5]) < 1e-9 && fabs(st[7]) < 1e-9);
    drive_base(fresh(), turn, 1.0, st);
    CHECK(st[7] > 0.1 && fabs(st[5]) < 1e-9 && fabs(st[6]) < 1e-9);
    /* Encoders: a wheel's channel counts its own motor. */
    void *p = fresh();
    const double one[4] = {0.3, 0, 0, 0};
    drive_base(p, one, 0.5, st);
    CHECK(ops->motor_angle(p, 5) > 1.0 && ops->motor_angle(p, 6) == 0.0);
    CHECK(isnan(ops->motor_angle(p, 9)) && isnan(ops->motor_angle(p, -1)));
}

int main(void)
{
    int id = xrf_plant_id("youbot");
    CHECK(id > 0);
    ops = xrf_plant_ops(id);
    CHECK(ops != NULL && ops->arm != NULL && ops->save && ops->load);
    struct xrf_plant_info info;
    CHECK(xrf_plant_describe(id, &info) == 0 && info.axes == 9 && info.state_len == 8);
    test_rest_pose_leans_on_the_stops();
    test_unpowered_the_arm_falls();
    test_hold_then_rest();
    test_hold_takes_hostile_measurements();
    test_hostile_snapshot_loads_physical();
    test_mecanum_odometry();
    return check_summary();
}
