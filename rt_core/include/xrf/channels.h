/*
 * xrf/channels.h — the one definition of the shared memory between a loop process and its host
 * side (appliance, CLI, ROS 2 bridge). The C/C++ runtime includes it; the Python side binds the
 * part between the cffi markers with cffi (appliance/xrflab/_cffi_build.py, for the package
 * xrflab.channels), so there is no second copy of this layout anywhere.
 *
 * Rules for the part between the markers (cffi parses it): plain integer #defines, structs of
 * fixed-width fields with explicit padding (no attributes), and prototypes. Every struct keeps
 * 8-byte alignment by construction so that C, C++ and cffi agree on offsets.
 *
 * Concurrency: every channel has exactly one writer side that never waits.
 *  - status:   seqlock, written by the loop each cycle, read by any number of hosts.
 *  - commands: bounded multi-producer ring (any host process may send), one consumer (the loop).
 *  - ros2xeno: latest-wins seqlock buffer, host writers serialise among themselves; the loop
 *              only try-reads (a torn read keeps last cycle's message).
 *  - telemetry, monitor: broadcast rings; the loop overwrites the oldest slot, each reader keeps
 *              its own cursor and learns exactly how many publications it lost.
 *  - log:      lossless single-producer/single-consumer ring; when full the loop drops the record
 *              and counts it (the loop never blocks), sequence numbers make the gap visible.
 *  - params:   a table of the controller's parameters (loop, before ready) and one pending set
 *              (host seqlock) the loop takes at a cycle boundary and answers (xrf/params.h).
 *  - doorbell: a futex word; the loop bumps it after publishing and wakes waiters only when some
 *              host announced it is waiting, at most once per doorbell period.
 */
#ifndef XRF_CHANNELS_H
#define XRF_CHANNELS_H

#include <stddef.h>
#include <stdint.h>

#include "params.h" /* struct xrf_params: the parameter block, a channel of its own */

#ifdef __cplusplus
extern "C" {
#endif

/* cffi-begin */
#define XRF_SHM_MAGIC 827740760 /* "XRF1" read as a little-endian uint32 */
#define XRF_SHM_VERSION \
    8 /* 7: the bench's channel count (xrf_shm.channels); 8: the simulated
                            * plant's snapshot (xrf_sim_snapshot) */

/* Board I/O channels (motor PWM + digital output, encoder + two input pins each). One ico board
 * has XRF_ICO_CHANNELS; a bench has up to XRF_MAX_BOARDS of them (several SPI devices, or a
 * simulated board that answers for several), so up to XRF_MAX_CHANNELS channels, numbered from
 * 1 across the boards (board b carries channels 4b+1 .. 4b+4). The bench's own count is
 * xrf_shm.channels; every array indexed by channel is XRF_MAX_CHANNELS long, so a loop over a
 * count (bounded by XRF_MAX_CHANNELS) never needs a second size. Python reads these through
 * cffi: no other file repeats 4 or 12. */
#define XRF_ICO_CHANNELS 4
#define XRF_MAX_BOARDS 3
#define XRF_MAX_CHANNELS 12 /* XRF_MAX_BOARDS * XRF_ICO_CHANNELS (checked in channels.c) */

#define XRF_NAME_MAX 64
#define XRF_REASON_MAX 128
#define XRF_SCHEMA_MAX 2048
#define XRF_MSG_MAX 512
#define XRF_PATH_MAX 512

#define XRF_HIST_BUCKETS 512
#define XRF_HIST_SUB_BITS 4 /* 16 sub-buckets per power of two: 6 % resolution */

/* Stages timed each cycle; index into xrf_status.hist. */
#define XRF_STAGE_WAKEUP 0 /* wake-up jitter: actual start - deadline */
#define XRF_STAGE_FPGA 1
#define XRF_STAGE_DATA 2
#define XRF_STAGE_CMD 3
#define XRF_STAGE_MONITOR 4
#define XRF_STAGE_HOOK 5
#define XRF_STAGE_LOGGER 6
#define XRF_STAGE_CYCLE 7 /* whole step(), wake-up to end of work */
#define XRF_STAGE_COUNT 8

/* FullStateMachine states and commands (XRF2_API.md): the one list of each, as X-macros. Every
 * other list is made from these: the XRF_STATE_<NAME> and XRF_CMD_<NAME> constants and their
 * counts (below the cffi part), the name tables and the reject text (channels.c), XRF2's
 * IDLE_STATE/START_CMD enums (xrf2/FullStateMachine.hpp), Python's names
 * (appliance/xrflab/channels/names.py: _cffi_build.py turns each list into the constants cffi
 * binds), and through the appliance the browser's state machine and command buttons
 * (GET /api/state-machine). The numbers are the wire's (shared memory, ROS XenoState/XenoCmd):
 * never renumber, add at the end.
 *
 * States: X(NAME, number). */
#define XRF_STATES(X)  \
    X(IDLE, 1)         \
    X(INITIALISING, 2) \
    X(INITIALISED, 3)  \
    X(RUN, 4)          \
    X(STOPPING, 5)     \
    X(STOPPED, 6)      \
    X(PAUSING, 7)      \
    X(PAUSED, 8)       \
    X(ERROR, 9)        \
    X(QUIT, 10)

/* Commands: X(NAME, name, number, safe). `name` is how hosts spell it (CLI, WebSocket, HTTP).
 * `safe` (1) marks a command that only brings a running controller to rest (stop, pause): any
 * user who may stop sends it without holding the bench lease (the appliance's auth), and the ROS
 * bridge passes it on even when the appliance's lease gate cannot be asked. */
#define XRF_CMDS(X)                 \
    X(INITIALISE, initialise, 1, 0) \
    X(START, start, 2, 0)           \
    X(STOP, stop, 3, 1)             \
    X(RESET, reset, 4, 0)           \
    X(PAUSE, pause, 5, 1)           \
    X(QUIT, quit, 6, 0)

/* The board transports a loop can use (XRF_TRANSPORT, xrf_info.transport): X(NAME, "name").
 * runtime.cpp opens each; hosts list them from here (names.TRANSPORTS: the CLI, the self-check). */
#define XRF_TRANSPORTS(X) \
    X(SIM, "sim")         \
    X(SPIDEV, "spidev")   \
    X(EVL_SPIDEV, "evl-spidev")

/* Why a command was rejected (xrf_status.reject_code). */
#define XRF_REJECT_NONE 0
#define XRF_REJECT_UNKNOWN 1     /* not a command number */
#define XRF_REJECT_NOT_ALLOWED 2 /* a command, but not in the current state */

/* Who sent a command (xrf_cmd_slot.source); informational, for the audit trail. */
#define XRF_SOURCE_UNKNOWN 0
#define XRF_SOURCE_CLI 1
#define XRF_SOURCE_APPLIANCE 2
#define XRF_SOURCE_ROS 3
#define XRF_SOURCE_LOOP 4 /* the loop itself, e.g. host heartbeat lost */

/* What the loop does when the host heartbeat goes stale (xrf_shm.host_timeout_action, set from
 * XRF_HOST_TIMEOUT_ACTION): X(NAME, "name", number). The runtime parses the variable and Python
 * (channels/names.py) names the actions from this list; the numbers are the segment's. */
#define XRF_HOST_LOST_ACTIONS(X) \
    X(IGNORE, "ignore", 0)       \
    X(PAUSE, "pause", 1)         \
    X(STOP, "stop", 2)

/* Why loop() returned (xrf_status.end_reason), written by the runtime as it leaves. A process
 * that ends while this is still XRF_END_NONE never left loop(): the controller called exit()
 * or crashed, which the host tells apart by the exit status. */
#define XRF_END_NONE 0
#define XRF_END_QUIT 1        /* the state machine reached QUIT (a quit command) */
#define XRF_END_CYCLE_LIMIT 2 /* XRF_MAX_CYCLES cycles done */
#define XRF_END_SIGNAL 3      /* SIGINT/SIGTERM: the runtime's safe stop */
#define XRF_END_RETURNED 4    /* step() returned non-zero or the program asked to stop */

#define XRF_CMD_SLOTS 64   /* power of two */
#define XRF_CMD_RESULTS 16 /* recent command outcomes kept in the status block */
#define XRF_TELEM_SLOTS 1024
#define XRF_MONITOR_SLOTS 256
#define XRF_MONITOR_TEXT 240
#define XRF_LOG_RING_BYTES 8388608
#define XRF_LOG_VARS_MAX 100
#define XRF_TIMING_SLOTS 16384 /* power of two: 16 s of cycles at 1 kHz, 1.6 s at 10 kHz */

/* Log writer (xrf_log_meta.writer): who drains the log ring into the file. */
#define XRF_LOG_WRITER_PROCESS 0 /* an in-band thread of the loop process */
#define XRF_LOG_WRITER_HOST 1    /* the appliance (set XRF_LOG_WRITER=host) */

struct xrf_hist {
    uint64_t count;
    uint64_t sum_ns;
    uint64_t min_ns;
    uint64_t max_ns;
    uint64_t buckets[XRF_HIST_BUCKETS];
};

/* Written once by the loop before it sets xrf_shm.ready; constant for the run. */
struct xrf_info {
    int32_t pid;
    uint32_t cycle_freq;
    uint32_t write_decimator_freq;
    uint32_t monitor_freq;
    uint32_t ros2xeno_size;
    uint32_t xeno2ros_size;
    int32_t rt_sched; /* 1 if the loop thread got real-time scheduling */
    int32_t cpu;      /* CPU the loop thread is pinned to, -1 if not pinned */
    int32_t priority; /* SCHED_FIFO priority, 0 if none */
    uint32_t doorbell_period_cycles;
    char backend[16];   /* "posix" | "evl" */
    char transport[16]; /* a name of XRF_TRANSPORTS */
    char sim[16];       /* "relbot" | "jiwy" | "" */
    char program[XRF_NAME_MAX];
    char ros2xeno_schema[XRF_SCHEMA_MAX]; /* normalised .msg text: "float64 steer_left\n..." */
    char xeno2ros_schema[XRF_SCHEMA_MAX];
};

/* Loop -> host, under the seqlock in `seq` (odd while the loop writes). */
struct xrf_status {
    uint32_t seq;
    int32_t state;
    int32_t last_error;        /* last negative hook return */
    int32_t last_cmd;          /* last accepted command */
    int32_t last_rejected_cmd; /* value of the last rejected command */
    int32_t reject_code;       /* XRF_REJECT_* of the last rejected command */
    uint32_t rejected_count;
    int32_t running;    /* 1 while loop() cycles, 0 after it returned */
    int32_t end_reason; /* XRF_END_*: why loop() returned; NONE while it runs */
    uint32_t pad0;
    uint64_t cmd_done;     /* ticket of the last command handled (accepted or rejected) */
    uint64_t cmd_rejected; /* ticket of the last rejected command */
    uint64_t cycles;
    uint64_t missed;
    int64_t t_start_ns;   /* CLOCK_MONOTONIC at the first deadline */
    int64_t heartbeat_ns; /* CLOCK_MONOTONIC at the start of the last cycle */
    uint64_t idle_ns;     /* total time slept */
    uint64_t demotions;   /* EVL: switches to in-band (EVL_T_WOSS); posix: 0 */
    uint64_t log_written; /* records put into the log ring */
    uint64_t log_lost;    /* records dropped because the ring was full */
    uint64_t telem_published;
    uint64_t monitor_dropped;  /* monitor.printf calls that did not fit */
    uint64_t host_lost;        /* times the host heartbeat went stale */
    uint64_t doorbell_dropped; /* doorbell rings the backend refused (EVL proxy ring full) */
    char reject_reason[XRF_REASON_MAX];
    /* Outcome of command ticket t in slot t % XRF_CMD_RESULTS: (t << 1) | rejected, with the
     * reason beside it, so a host learns its own command's fate even when others follow. */
    uint64_t cmd_results[XRF_CMD_RESULTS];
    char cmd_reasons[XRF_CMD_RESULTS][XRF_REASON_MAX];
    struct xrf_hist hist[XRF_STAGE_COUNT];
};

struct xrf_cmd_slot {
    uint64_t seq; /* Vyukov bounded-queue sequence */
    uint64_t ticket;
    int64_t t_sent_ns;
    int32_t cmd;
    int32_t source;
};

struct xrf_cmd_ring {
    uint64_t head; /* producers claim with compare-and-swap */
    uint64_t pad0[7];
    uint64_t tail; /* the loop only */
    uint64_t pad1[7];
    struct xrf_cmd_slot slot[XRF_CMD_SLOTS];
};

/* Host -> loop, latest wins. `seq` odd while a host writes; writers claim it by CAS. */
struct xrf_data_in {
    uint32_t seq;
    uint32_t size;
    uint64_t writes;
    int64_t t_sent_ns;
    uint64_t pad;
    uint8_t data[XRF_MSG_MAX];
};

/* Header of a ring of fixed-size slots (broadcast or SPSC). */
struct xrf_ring {
    uint64_t head; /* publications so far; written by the producer only */
    uint64_t pad0[7];
    uint64_t tail; /* SPSC only: records consumed; written by the consumer only */
    uint64_t pad1[7];
    uint32_t slots;     /* number of slots */
    uint32_t slot_size; /* bytes per slot, a multiple of 8, including the slot header */
    uint64_t dropped;   /* SPSC only: records the producer could not store */
    uint64_t pad2[6];
};

/* Every slot of a ring starts with this header. Broadcast rings use `seq` as a per-slot seqlock:
 * 2n+1 while publication n is written, 2n+2 once it is complete. */
struct xrf_slot_hdr {
    uint64_t seq;
    uint64_t cycle;
    int64_t t_ns;
};

/* One telemetry publication (at write_decimator_freq): Xeno2Ros plus the raw I/O. */
struct xrf_telemetry {
    struct xrf_slot_hdr hdr;
    int32_t state;
    /* Per channel, the bench's count (xrf_shm.channels) used, the rest zero. */
    int32_t enc[XRF_MAX_CHANNELS];
    uint8_t din[2 * XRF_MAX_CHANNELS]; /* channel1_1, channel1_2, channel2_1, ... */
    int16_t pwm[XRF_MAX_CHANNELS];
    uint8_t dout[XRF_MAX_CHANNELS];
    uint32_t size; /* bytes of xeno2ros in data */
    uint32_t pad;
    int64_t ros2xeno_t_sent_ns; /* t_sent_ns of the Ros2Xeno in use, for latency measurement */
    uint8_t data[XRF_MSG_MAX];
};

struct xrf_monitor_line {
    struct xrf_slot_hdr hdr;
    uint32_t len;
    char text[XRF_MONITOR_TEXT];
    uint32_t pad;
};

struct xrf_log_var {
    char name[XRF_NAME_MAX];
    int32_t type;   /* XRF_LOG_* (xrf/logformat.h: the codes and the file format) */
    int32_t offset; /* byte offset in the packed record */
};

/* Set by the logger's initialise(); `ready` is stored last. */
struct xrf_log_meta {
    uint32_t ready;
    uint32_t nvars;
    uint32_t record_size; /* payload bytes of one record (the packed struct) */
    uint32_t writer;      /* XRF_LOG_WRITER_* */
    uint64_t generation;  /* bumped by each initialise() that changes the file */
    uint32_t file_mode;   /* permission bits for a new file (XenoFileHandler's mode) */
    uint32_t pad;
    char path[XRF_PATH_MAX];
    struct xrf_log_var vars[XRF_LOG_VARS_MAX];
};

/* One cycle's framework timing (XRF_LOG_TIMING=1): a log record like the logger's, described
 * by xrf_shm.timing_meta (xrf_timing_meta_init) and written to its own log file, so every
 * decoder reads it. Durations in ns; -1 for a stage that did not run in that cycle (the
 * monitor runs at its own rate; a plain XenoFrtLoop has no FPGA stage). */
struct xrf_timing_record {
    struct xrf_slot_hdr hdr;
    int64_t wakeup_ns; /* start of the cycle - its deadline: the wake-up jitter */
    int64_t fpga_ns;
    int64_t data_ns;
    int64_t cmd_ns;
    int64_t monitor_ns;
    int64_t hook_ns; /* the student's controller */
    int64_t logger_ns;
    int64_t cycle_ns; /* wake-up to end of work */
    int32_t missed;   /* periods passed over after this cycle (it woke or ended late); 0 on time */
    uint8_t pad[4];
};

/* The simulated board's outputs as the plant sees them. The host may force them to zero after
 * the loop died (the simulated counterpart of an FPGA RESET). */
struct xrf_sim_outputs {
    uint32_t active;     /* 1 while a simulated board is in use */
    uint32_t forced_off; /* set by the host: the plant ignores pwm from now on */
    int16_t pwm[XRF_MAX_CHANNELS];
    uint8_t dout[XRF_MAX_CHANNELS];
    /* The digital outputs while forced_off, set before it by the safety watcher: all zero, or
     * the brake's on for the safe reaction `brake` (xrf/watch.h). */
    uint8_t forced_dout[XRF_MAX_CHANNELS];
    double plant[8]; /* plant state for viewers: jiwy pan, tilt (rad); relbot x, y, theta */
};

/* Simulated time (XRF_VIRTUAL_TIME, docs/rt_core/runtime.md "Simulated time"): the loop on the
 * simulated board does not sleep, its clock skips each cycle's idle time. A host that feeds
 * inputs at exact loop times holds the loop: no cycle whose index (status.cycles) is >= run_until
 * starts until the host raises it (a command in the ring lets one cycle run, to take it). */
struct xrf_vtime {
    uint32_t active; /* loop: 1 when this run is in simulated time (set before ready) */
    uint32_t pad;
    uint64_t run_until; /* host: cycles the loop may run; UINT64_MAX: free-running */
};

/* The simulated plant's dynamic state (its `save` op, rt_core/src/plant.h), written by the board
 * at each transfer under the seqlock `seq` (odd while it writes), for the safety watcher: once
 * the loop process is gone nothing else steps the plant, so for the safe reaction `hold` the
 * watcher loads this into its own copy of the plant and steps it on (xrf/watch.h). The loop
 * (student code) can write anything here: the watcher takes only the number of values its own
 * plant row says, and the plant's `load` keeps every value finite and physical. */
#define XRF_SIM_SNAPSHOT_MAX 32
struct xrf_sim_snapshot {
    uint32_t seq;
    uint32_t n; /* values in v (informational: readers use their own plant's count) */
    double v[XRF_SIM_SNAPSHOT_MAX];
};

struct xrf_shm {
    uint32_t magic;
    uint32_t version;
    uint32_t size;  /* sizeof(struct xrf_shm), checked by every reader */
    uint32_t ready; /* stored last by the loop once info is complete */
    /* The bench's channel count, 1..XRF_MAX_CHANNELS: written by the host that creates the
     * segment (the appliance, from the bench profile), else by the loop at start (its plant's
     * count on the simulated board, else XRF_ICO_CHANNELS). The loop can rewrite it at any
     * time: a reader takes it once at attach (xrf_shm_check, into xrf_shm_geom.channels) or
     * bounds it (xrf_shm_channels), never uses it as it is. */
    uint32_t channels;
    uint32_t pad_channels;
    struct xrf_info info;

    /* host -> loop */
    int64_t host_heartbeat_ns;    /* CLOCK_MONOTONIC, written by the supervising host */
    uint32_t host_timeout_ms;     /* 0: no host supervision */
    uint32_t host_timeout_action; /* XRF_HOST_LOST_ACTION_* */

    /* doorbell (futex word) */
    uint32_t doorbell;
    uint32_t doorbell_waiters;

    struct xrf_status status;
    struct xrf_cmd_ring cmd;
    struct xrf_data_in ros2xeno;
    struct xrf_sim_outputs sim;

    struct xrf_ring telem_ring;
    struct xrf_telemetry telem[XRF_TELEM_SLOTS];
    struct xrf_ring monitor_ring;
    struct xrf_monitor_line monitor[XRF_MONITOR_SLOTS];

    struct xrf_log_meta log_meta;
    struct xrf_ring log_ring;
    uint8_t log_data[XRF_LOG_RING_BYTES];

    /* per-cycle framework timing, when the loop runs with XRF_LOG_TIMING=1 */
    struct xrf_log_meta timing_meta;
    struct xrf_ring timing_ring;
    struct xrf_timing_record timing[XRF_TIMING_SLOTS];

    /* live parameter tuning (xrf/params.h): table by the loop, sets by the host */
    struct xrf_params params;
    struct xrf_vtime vtime;
    struct xrf_sim_snapshot sim_snapshot;
};

/* Layout and lifecycle (loop side). */
void xrf_shm_init(struct xrf_shm *shm);
void xrf_shm_publish_ready(struct xrf_shm *shm);
/* Describe the timing records in `m` (names, types, offsets; file `path`, written by `writer`)
 * and publish it (ready last). The caller initialises timing_ring first. */
void xrf_timing_meta_init(struct xrf_log_meta *m, uint32_t writer, const char *path);

/* Histograms: log-linear buckets over nanoseconds. */
int xrf_hist_bucket(uint64_t ns);
uint64_t xrf_hist_bucket_low(int bucket);
void xrf_hist_add(struct xrf_hist *h, uint64_t ns);

/* Status seqlock. */
void xrf_status_write_begin(struct xrf_status *s);
void xrf_status_write_end(struct xrf_status *s);
/* Reader: a consistent copy of the block into out; 0, or -EAGAIN when it stayed locked (or kept
 * changing) for a bounded number of tries (retry after a pause, for a bounded time). */
int xrf_status_read(const struct xrf_status *s, struct xrf_status *out);

/* Commands. Returns the ticket (> 0), -EAGAIN when the ring is full, -EBUSY when the slot seqs
 * kept the sender from claiming one for a bounded number of tries, -EPROTO for a head no
 * ticket can follow. */
int64_t xrf_cmd_send(struct xrf_cmd_ring *r, int32_t cmd, int32_t source, int64_t t_sent_ns);
int xrf_cmd_poll(struct xrf_cmd_ring *r, struct xrf_cmd_slot *out); /* 1 taken, 0 empty */

/* Ros2Xeno, latest wins. Host: 0, -EMSGSIZE, -EBUSY (held by another writer, or a dead one, for a
 * bounded number of tries). */
int xrf_data_in_write(struct xrf_data_in *d, const void *data, uint32_t size, int64_t t_sent_ns);
/* Loop side: copies into out only if a complete message newer than *last_seq exists.
 * Returns 1 copied, 0 nothing new (or a write in progress: keep the old one). */
int xrf_data_in_try_read(struct xrf_data_in *d, uint32_t *last_seq, void *out, uint32_t size,
                         int64_t *t_sent_ns);

/* Rings of fixed-size slots. `slots` points at slot 0. Producer side (the loop): these take the
 * geometry from the ring header, which the loop itself set. */
void xrf_ring_init(struct xrf_ring *r, uint32_t slots, uint32_t slot_size);
void *xrf_bcast_begin(struct xrf_ring *r, void *slots); /* producer */
void xrf_bcast_commit(struct xrf_ring *r, void *slot);  /* producer */
void *xrf_spsc_begin(struct xrf_ring *r, void *slots);  /* NULL when full (counted in dropped) */
void xrf_spsc_commit(struct xrf_ring *r, void *slot);
uint32_t xrf_log_slots_for(uint32_t record_size, uint32_t ring_bytes, uint32_t *slot_size);

/* ---- reading a segment: everything in it is hostile input ------------------------------------
 * The segment is written by the loop, i.e. by a student's program, at any time: no size, offset,
 * count, index or name in it is used unbounded. A reader (the appliance, the CLI, the ROS 2
 * bridge, and the loop's own in-band helper, which uses the same code) takes each ring's
 * geometry ONCE into its own memory -- at attach (xrf_shm_check) or when a log channel publishes
 * its layout (xrf_log_meta_check) -- checked against the space the layout gives that ring, and
 * passes that copy to the readers below. They never read slots/slot_size from the segment,
 * bound every head, tail and count they do read, copy only sizes the reader fixed, and give up
 * after a bounded number of retries where a (dead or hostile) loop holds a lock.
 *
 * Errors: -EPROTO the segment broke the protocol (a reader stops trusting it: the appliance stops
 * the run with a corrupt-channel alarm); -EINVAL the caller's own arguments are wrong; -EAGAIN
 * nothing consistent to take now (retry later). The loop's steady-state path uses none of these. */

/* A ring's geometry as the reader holds it (never in the segment). */
struct xrf_ring_geom {
    uint32_t slots;     /* power of two, 1 .. 2^30 */
    uint32_t slot_size; /* multiple of 8, >= sizeof(struct xrf_slot_hdr) */
};

/* The geometry of every fixed ring of a segment, taken at attach. */
struct xrf_shm_geom {
    struct xrf_ring_geom telem;
    struct xrf_ring_geom monitor;
    uint32_t channels; /* the bench's channel count, 1..XRF_MAX_CHANNELS, as it was at attach */
    uint32_t pad;
};

/* Checks that (slots, slot_size) is a ring whose slots fit `capacity` bytes (-EINVAL if not),
 * and that the ring header r says the same (read once; -EPROTO if not); fills *g. */
int xrf_ring_geom_check(const struct xrf_ring *r, uint32_t slots, uint32_t slot_size,
                        uint64_t capacity, struct xrf_ring_geom *g);
/* At attach: `mapped` bytes are mapped at shm (-EINVAL when fewer than sizeof(struct xrf_shm):
 * the caller must not read it); magic, version and size are this layout's and the telemetry
 * and monitor rings are as xrf_shm_init made them and the channel count is 1..XRF_MAX_CHANNELS
 * (-EPROTO otherwise); fills *g. */
int xrf_shm_check(const struct xrf_shm *shm, uint64_t mapped, struct xrf_shm_geom *g);
/* The segment's channel count read now, clamped into 1..XRF_MAX_CHANNELS, so it can index no
 * array past its end. For a reader that did not keep xrf_shm_geom.channels. */
uint32_t xrf_shm_channels(const struct xrf_shm *shm);
/* A log channel's layout, once `m` is ready: copies *m once into *out and checks the copy --
 * writer known, nvars <= XRF_LOG_VARS_MAX, every variable of a known type and inside
 * record_size, names and path NUL-terminated, record_size fits a slot of a ring of
 * `capacity` bytes -- and that ring r has the geometry xrf_log_slots_for gives, as the loop's
 * logger set it (*g). *tail: the consumer's position, read from the segment this once; the
 * reader keeps it in its own memory from here on. 0; -EAGAIN not ready, or the generation
 * changed during the copy; -EPROTO. out->generation is the generation the copy belongs to. */
int xrf_log_meta_check(const struct xrf_log_meta *m, const struct xrf_ring *r, uint32_t capacity,
                       struct xrf_log_meta *out, struct xrf_ring_geom *g, uint64_t *tail);

/* Broadcast reader: copies publication *cursor (g->slot_size bytes: `out` holds at least that)
 * and advances the cursor. 1 copied, 0 nothing new, -EPROTO the head went back behind this
 * reader or the ring header no longer says g (compared, never used: a loop never changes it). Publications overwritten before this reader got to them are added to *lost and
 * skipped (the cursor moves to the oldest one still present). */
int xrf_bcast_read_g(const struct xrf_ring *r, const struct xrf_ring_geom *g, const void *slots,
                     uint64_t *cursor, void *out, uint64_t *lost);
/* SPSC consumer at position `tail` (its own copy): the longest run of ready slots that is
 * contiguous in memory (for one write()). Returns the number of slots, 1 .. g->slots, and sets
 * *first; 0 when empty; -EPROTO when the head claims more records than the ring holds (or is
 * behind the tail), or the ring header no longer says g (a log channel set up again: take its
 * layout anew, see its generation). */
int xrf_spsc_peek_run_g(const struct xrf_ring *r, const struct xrf_ring_geom *g, const void *slots,
                        uint64_t tail, const void **first);
/* SPSC consumer: gives n slots back (*tail += n, published for the producer). */
void xrf_spsc_release_g(struct xrf_ring *r, uint64_t *tail, uint32_t n);

/* Doorbell. */
int xrf_doorbell_should_ring(struct xrf_shm *shm); /* loop: bump the word; 1 if someone waits */
int xrf_doorbell_wake(struct xrf_shm *shm);        /* in-band: FUTEX_WAKE all waiters */
/* Host: wait until the word differs from `seen` or timeout_ms passes. Returns the new value. */
uint32_t xrf_doorbell_wait(struct xrf_shm *shm, uint32_t seen, int timeout_ms);

/* The command table of FullStateMachine: the state `cmd` leads to from `state`, or
 * -XRF_REJECT_UNKNOWN / -XRF_REJECT_NOT_ALLOWED. The loop and the host both use it. */
int32_t xrf_cmd_transition(int32_t state, int32_t cmd);
/* The state a state's hook completing (returning 1) leads to, or 0 where completing leads
 * nowhere (IDLE, STOPPED, PAUSED, ERROR, QUIT). FullStateMachine::step follows it; the dashboard
 * draws it (GET /api/state-machine), so the whole state machine is this table and the one above. */
int32_t xrf_state_complete(int32_t state);
/* Human-readable reason for a rejection, into buf (always NUL-terminated). */
void xrf_cmd_reject_reason(int32_t state, int32_t cmd, char *buf, size_t len);

/* Names for humans (static strings). */
const char *xrf_state_name(int32_t state);
const char *xrf_cmd_name(int32_t cmd);
/* 1 for a command XRF_CMDS marks safe (stop, pause), else 0 (also for a number no command has). */
int xrf_cmd_safe(int32_t cmd);
/* The name of transport XRF_TRANSPORT_<NAME> (0 .. XRF_TRANSPORT_COUNT - 1), else NULL. */
const char *xrf_transport_name(int32_t transport);
/* The name of host-lost action XRF_HOST_LOST_ACTION_<NAME>, else NULL; and the action a name
 * spells, else -EINVAL. */
const char *xrf_host_lost_action_name(int32_t action);
int32_t xrf_host_lost_action_parse(const char *name);
/* cffi-end */

/* The constants of the lists above, for C and C++ (cffi gets the same names from _cffi_build.py,
 * which reads the lists; an enum because cffi cannot parse a function-like macro). */
#define XRF_STATE_CONST_(NAME, number) XRF_STATE_##NAME = number,
#define XRF_CMD_CONST_(NAME, name, number, safe) XRF_CMD_##NAME = number,
#define XRF_COUNT_ONE_(...) +1
enum { XRF_STATES(XRF_STATE_CONST_) XRF_STATE_COUNT = 0 XRF_STATES(XRF_COUNT_ONE_) };
enum { XRF_CMDS(XRF_CMD_CONST_) XRF_CMD_COUNT = 0 XRF_CMDS(XRF_COUNT_ONE_) };
#define XRF_TRANSPORT_CONST_(NAME, name) XRF_TRANSPORT_##NAME,
enum { XRF_TRANSPORTS(XRF_TRANSPORT_CONST_) XRF_TRANSPORT_COUNT };
#define XRF_HOST_LOST_ACTION_CONST_(NAME, name, number) XRF_HOST_LOST_ACTION_##NAME = number,
enum {
    XRF_HOST_LOST_ACTIONS(XRF_HOST_LOST_ACTION_CONST_) XRF_HOST_LOST_ACTION_COUNT =
        0 XRF_HOST_LOST_ACTIONS(XRF_COUNT_ONE_)
};

#ifdef __cplusplus
}
#endif

#endif /* XRF_CHANNELS_H */
