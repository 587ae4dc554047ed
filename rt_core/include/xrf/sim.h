/*
 * xrf/sim.h — the simulated ico board: answers the 12-byte protocol byte for byte and drives a
 * plant model (one of the plant table's, xrf/plants.h) advanced in time at each transfer.
 * Faults can be injected so the self-check and the error paths are testable without hardware.
 */
#ifndef XRF_SIM_H
#define XRF_SIM_H

#include <stdint.h>

#include "xrf/channels.h"
#include "xrf/ico.h"

#ifdef __cplusplus
extern "C" {
#endif

/* Ids of the first two rows of the plant table (rt_core/src/plants.c); other plants are reached
 * by name (xrf_sim_robot_from_name) or id (xrf/plants.h). */
#define XRF_SIM_RELBOT 1
#define XRF_SIM_JIWY 2

/* cffi-begin */
struct xrf_sim_faults {
    int no_init_reply;      /* INIT answers without the 11 in byte 4 */
    uint8_t dead_encoder;   /* bit n-1: encoder n never counts */
    uint8_t reversed_motor; /* bit n-1: motor n turns the other way */
    uint8_t stuck_input;    /* bit k: input pin k (0..7, order of xrf_ico_in.din) is stuck */
    uint8_t stuck_value;    /* bit k: the value it is stuck at */
    int corrupt_echo;       /* TEST replies with flipped bits */
    uint32_t slow_link_us;  /* each transfer takes at least this long */
    uint8_t loopback;       /* bit n-1: digital output n is wired back to input pin 1 of n */
    uint32_t start_seed;    /* > 0: the plant starts from the pose this seed draws (if it can) */
    uint8_t absent_board;   /* bit b: ico board b + 1 (2, 3) of a bench is not there: every reply
                             * of it is zeros (the self-check's "board.B" step) */
    uint32_t stall_ms;      /* every SIM_STALL_EVERY-th transfer holds its caller this long (a
                             * machine that stalls the self-check: its counts may wrap) */
};

/* Parses "dead_encoder=2,reversed_motor=1,no_init,corrupt_echo,stuck_input=3:1,slow_link_us=200,
 * loopback=1,start=7,absent_board=2,stall_ms=300" (channels and boards 1-based, stuck_input=<pin 1..8>:<value>, start=<seed 1..2^32-1>:
 * the plant's start pose, for plants that start anywhere). Returns 0 or -EINVAL. */
int xrf_sim_parse_faults(const char *spec, struct xrf_sim_faults *faults);

/* Opens a simulated board with the given plant (an id of the plant table). The plant advances
 * by the CLOCK_MONOTONIC time since the previous transfer (vDSO read, no system call), in
 * sub-steps of at most 100 us; with fixed_dt_s > 0 it advances by exactly that per transfer
 * instead (deterministic tests). `outputs` (may be NULL) mirrors the outputs and plant state into
 * shared memory and lets the host force the outputs off. */
int xrf_sim_open(int robot, const struct xrf_sim_faults *faults, double fixed_dt_s,
                 struct xrf_sim_outputs *outputs, struct xrf_ico_transport **out);
/* The same on a bench of `channels` channels (0: the plant row's count; else at least that and at
 * most XRF_MAX_CHANNELS, -EINVAL otherwise): the board answers as ceil(channels / 4) ico boards
 * (xrf_ico_transport.boards, xfer_board), channels beyond the bench's count read 0 and drive
 * nothing. The plant advances at board 0's transfers (every loop exchanges a frame with board 0
 * each cycle: IcoIo::update_io), the other boards' transfers only read and set registers. */
int xrf_sim_open_bench(int robot, int channels, const struct xrf_sim_faults *faults,
                       double fixed_dt_s, struct xrf_sim_outputs *outputs,
                       struct xrf_ico_transport **out);
/* A plant's id by name ("relbot", "jiwy", ...: xrf_plant_id), else -EINVAL. */
int xrf_sim_robot_from_name(const char *name);

/* The watcher's board path tested without hardware (docs/developers/safety.md, "hold on a real
 * bench"): this board plays the physical arm a loop process drives through its own simulated
 * board. Until a frame that sets outputs (ALL, PWM_n, RESET) arrives, each transfer first takes
 * the plant's state from the loop's snapshot when the loop's board wrote a new one
 * (loop_shm->sim_snapshot: only this plant's count of values, sanitised by its `load`) with the
 * loop's outputs (loop_shm->sim.pwm), and in between steps the plant by those outputs (a loop
 * that missed cycles or is gone: the FPGA keeps driving what it was last told), so read-only
 * frames (ENC_n) see a continuous arm the loop moves; from that frame on the board steps the
 * plant by its own registers. -EINVAL if `t` is not a simulated board. */
int xrf_sim_follow(struct xrf_ico_transport *t, const struct xrf_shm *loop_shm);
/* A RESET of board `board` (0-based) arrives before the board's next transfer, from another
 * thread (a student's program resetting the counters mid-run, for tests of the watcher's
 * checks): an atomic request, safe while another thread exchanges frames. */
int xrf_sim_inject_reset(struct xrf_ico_transport *t, int board);
/* cffi-end */

/* Simulated time: the board reads `now_ns` (the loop's virtual CLOCK_MONOTONIC, ns) instead of
 * CLOCK_MONOTONIC to know how far to advance the plant, so the plant moves on the loop's clock.
 * NULL: back to CLOCK_MONOTONIC. -EINVAL if `t` is not a simulated board. */
int xrf_sim_set_clock(struct xrf_ico_transport *t, int64_t (*now_ns)(void));

/* The plant's snapshot (struct xrf_sim_snapshot, for the safety watcher's `hold`) goes to
 * `snapshot` at each transfer from now on (NULL: nowhere). -EINVAL if `t` is not a simulated
 * board. */
int xrf_sim_set_snapshot(struct xrf_ico_transport *t, struct xrf_sim_snapshot *snapshot);

/* Plant state for tests and viewers, as the plant's table row names it (xrf_plant_info.state):
 * e.g. jiwy {pan, tilt, pan_rate, tilt_rate} (rad, rad/s at the camera), relbot {x, y, theta,
 * wheel_left, wheel_right} (m, rad, wheel rad/s). */
int xrf_sim_plant_state(struct xrf_ico_transport *t, double *state, int n);

#ifdef __cplusplus
}
#endif

#endif /* XRF_SIM_H */
