/*
 * xrf-watch — the safety watcher as a process of its own, for the one fault the appliance's
 * watcher thread cannot cover: the appliance itself dying (kill -9, an OOM kill). The thread dies
 * with it, while the loop runs on (its launcher is not tied to the appliance) with nobody to make
 * the outputs safe if it then fails, and for an arm nobody to put it down.
 *
 * Started per run beside the appliance's thread, in a session of its own (not tied to the
 * appliance's life), it runs the same watcher (xrf/watch.h) with host_only: when the appliance
 * (--host) dies first it kills the loop (through a pidfd) and carries out the bench's safe
 * reaction (`hold`: the arm held, lowered to its rest pose, then zero); when the loop ends first
 * it leaves, the appliance's own watcher having handled it. One JSON line on stdout at the end.
 *
 * When it acted, what it did is written as a small record into the run's folder (--record-dir-fd,
 * the folder as the appliance opened it, and --record NAME): once when the outputs are safe
 * ("done": 0, the arm still being lowered) and again at the end. Nobody reads our stdout then
 * (the appliance is gone); the restarted appliance reads the record back and shows it with the
 * run (server/runs/orphans.py). The folder is the guest's to write: the record is a new file made
 * with O_EXCL | O_NOFOLLOW beside the name, relative to the folder's descriptor (never a path:
 * the folder's parents are not walked again), then renamed over the name; a link or anything
 * else planted at the name is replaced, never written through. The reader treats it as untrusted
 * anyway (bounded, validated): the guest may replace it afterwards.
 *
 *   xrf-watch --shm PATH|--shm-fd FD --loop PID --host PID [--reaction zero|brake|hold] [--plant NAME]
 *             [--brake-channel N] [--spi DEVICE[,DEVICE...]] [--rt-priority N]
 *             [--counts-per-rev N] [--enc-inverted MASK] [--pwm-reversed MASK]
 *             [--record-dir-fd FD --record NAME]
 * (--spi: one device per ico board, board 1 first; --counts-per-rev, --enc-inverted and
 * --pwm-reversed: a real bench's `hold`, from the bench profile, xrf/watch.h.)
 */
#define _GNU_SOURCE

#include <errno.h>
#include <signal.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <poll.h>
#include <stdint.h>
#include <sys/eventfd.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#include "xrf/channels.h"
#include "xrf/plants.h"
#include "xrf/watch.h"

static int usage(const char *why)
{
    fprintf(stderr,
            "xrf-watch: %s\nusage: xrf-watch --shm PATH --loop PID --host PID [--reaction NAME] "
            "[--plant NAME] [--brake-channel N] [--spi DEVICE] [--rt-priority N] "
            "[--record-dir-fd FD --record NAME]\n",
            why);
    return 2;
}

static int parse_int(const char *s, long lo, long hi, long *out)
{
    char *end = NULL;
    errno = 0;
    long v = strtol(s, &end, 10);
    if (errno || end == s || *end != '\0' || v < lo || v > hi)
        return -1;
    *out = v;
    return 0;
}

static int64_t clock_ns(clockid_t id)
{
    struct timespec ts;
    clock_gettime(id, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

/* A record name is one plain name in the run's folder: no folder part, no hidden file (the
 * temporary files beside it are hidden), short. */
static int plain_name(const char *name)
{
    size_t n = strlen(name);
    if (n == 0 || n > 64 || name[0] == '.')
        return 0;
    for (size_t i = 0; i < n; i++) {
        char c = name[i];
        if (!((c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '-' || c == '_' || c == '.'))
            return 0;
    }
    return 1;
}

/* What the watcher did, as one JSON object (bounded: a few hundred bytes), written as a whole
 * into the run's folder: a new hidden file beside `name` (O_EXCL | O_NOFOLLOW: nothing planted
 * is opened or followed), synced, renamed over `name` inside the same folder. Times are relative
 * to the fault (event_ns) but for event_unix_ms, the wall-clock time of the fault for people.
 * 0 or -errno (the record is then missing, which the reader says; a run folder the guest filled
 * to its limit refuses it with ENOSPC). */
static int write_record(int dirfd, const char *name, const struct xrf_watch_result *res, int done,
                        long loop)
{
    int64_t mono = clock_ns(CLOCK_MONOTONIC), real = clock_ns(CLOCK_REALTIME);
    long long event_unix_ms = (long long)((real - (mono - res->event_ns)) / 1000000);
    char buf[512];
    int n = snprintf(buf, sizeof buf,
                     "{\"xrf_watch\": 1, \"pid\": %d, \"loop\": %ld, \"reason\": %d, \"done\": %d, "
                     "\"event_unix_ms\": %lld, \"safe_after_ns\": %lld, \"rest_after_ns\": %lld, "
                     "\"drop_urad\": %d, \"hold_phase\": %d, \"kill_status\": %d, "
                     "\"hold_status\": %d}\n",
                     (int)getpid(), loop, res->reason, done, event_unix_ms,
                     (long long)(res->safe_ns - res->event_ns),
                     (long long)(res->rest_ns ? res->rest_ns - res->event_ns : 0), res->drop_urad,
                     res->hold_phase, res->kill_status, res->hold_status);
    if (n < 0 || (size_t)n >= sizeof buf)
        return -EOVERFLOW;
    char tmp[96];
    snprintf(tmp, sizeof tmp, ".%s.%d.%lld.tmp", name, (int)getpid(), (long long)mono);
    int fd =
        openat(dirfd, tmp, O_WRONLY | O_CREAT | O_EXCL | O_NOFOLLOW | O_CLOEXEC | O_NOCTTY, 0640);
    if (fd < 0)
        return -errno;
    int r = 0;
    for (int off = 0; off < n && r == 0;) {
        ssize_t w = write(fd, buf + off, (size_t)(n - off));
        if (w < 0 && errno != EINTR)
            r = -errno;
        else if (w == 0)
            r = -EIO; /* a regular file takes bytes or says why: never loop on nothing */
        else if (w > 0)
            off += (int)w;
    }
    if (r == 0 && fsync(fd) != 0)
        r = -errno;
    close(fd);
    if (r == 0 && renameat(dirfd, tmp, dirfd, name) != 0)
        r = -errno;
    if (r != 0)
        unlinkat(dirfd, tmp, 0);
    return r;
}

int main(int argc, char **argv)
{
    long shm_fd = -1, record_fd = -1;
    const char *record = NULL;
    const char *shm_path = NULL, *reaction = "zero", *plant = NULL, *spi = "";
    long loop = 0, host = 0, brake = 0, prio = 0, cpr = 0, enc_inv = 0, pwm_rev = 0;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char *v = i + 1 < argc ? argv[i + 1] : NULL;
        if (v == NULL)
            return usage("every option takes a value");
        i++;
        if (strcmp(a, "--shm") == 0)
            shm_path = v;
        else if (strcmp(a, "--shm-fd") == 0 && parse_int(v, 0, 0x7fffffff, &shm_fd) == 0)
            continue;
        else if (strcmp(a, "--loop") == 0 && parse_int(v, 1, 0x7fffffff, &loop) == 0)
            continue;
        else if (strcmp(a, "--host") == 0 && parse_int(v, 1, 0x7fffffff, &host) == 0)
            continue;
        else if (strcmp(a, "--reaction") == 0)
            reaction = v;
        else if (strcmp(a, "--plant") == 0)
            plant = v;
        else if (strcmp(a, "--spi") == 0)
            spi = v;
        else if (strcmp(a, "--brake-channel") == 0 && parse_int(v, 1, 4, &brake) == 0)
            continue;
        else if (strcmp(a, "--rt-priority") == 0 && parse_int(v, 0, 99, &prio) == 0)
            continue;
        else if (strcmp(a, "--record-dir-fd") == 0 && parse_int(v, 0, 0x7fffffff, &record_fd) == 0)
            continue;
        else if (strcmp(a, "--record") == 0 && plain_name(v))
            record = v;
        else if (strcmp(a, "--counts-per-rev") == 0 && parse_int(v, 0, 10000000, &cpr) == 0)
            continue;
        else if (strcmp(a, "--enc-inverted") == 0 && parse_int(v, 0, 0xfff, &enc_inv) == 0)
            continue;
        else if (strcmp(a, "--pwm-reversed") == 0 && parse_int(v, 0, 0xfff, &pwm_rev) == 0)
            continue;
        else
            return usage("unknown option or bad value");
    }
    /* Our stdout may be a pipe to the host that is gone: the report must not kill us. */
    signal(SIGPIPE, SIG_IGN);
    if ((shm_path == NULL) == (shm_fd < 0) || loop == 0 || host == 0)
        return usage("--shm or --shm-fd, --loop and --host are needed");
    if ((record == NULL) != (record_fd < 0))
        return usage("--record-dir-fd and --record go together");
    if (record_fd >= 0) {
        struct stat rst;
        if (fstat((int)record_fd, &rst) != 0 || !S_ISDIR(rst.st_mode))
            return usage("--record-dir-fd is not an open folder");
        fcntl((int)record_fd, F_SETFD, FD_CLOEXEC);
    }
    struct xrf_watch_config cfg;
    memset(&cfg, 0, sizeof cfg);
    cfg.pid = (int)loop;
    cfg.host_pid = (int)host;
    cfg.host_only = 1;
    cfg.safe_reaction = xrf_safe_reaction_parse(reaction);
    if (cfg.safe_reaction < 0)
        return usage("unknown --reaction");
    cfg.brake_channel = (int32_t)brake;
    cfg.rt_priority = (int)prio;
    /* Told when the watcher acted (or the loop ended first): then the first record. */
    cfg.notify_fd = record_fd >= 0 ? eventfd(0, EFD_CLOEXEC) : -1;
    cfg.check_ns = 20000000;
    if (strlen(spi) >= sizeof cfg.spi_device)
        return usage("--spi path too long");
    memcpy(cfg.spi_device, spi, strlen(spi) + 1);
    cfg.spi_speed_hz = 31000000;
    cfg.force_sim = spi[0] == '\0';
    cfg.enc_counts_per_rev = (int32_t)cpr;
    cfg.enc_inverted = (uint32_t)enc_inv;
    cfg.pwm_reversed = (uint32_t)pwm_rev;
    if (plant != NULL) {
        cfg.plant = xrf_plant_id(plant);
        if (cfg.plant < 0)
            return usage("unknown --plant");
    }

    /* The segment as the appliance opened it: checked like any reader does (the loop wrote it). */
    /* The appliance hands over its own descriptor of the run's segment (a sealed memfd): a
     * path in the run's /dev/shm folder is the loop's to replace. */
    int fd = shm_fd >= 0 ? (int)shm_fd : open(shm_path, O_RDWR | O_CLOEXEC | O_NOFOLLOW);
    if (shm_path == NULL)
        shm_path = "--shm-fd";
    if (fd < 0) {
        fprintf(stderr, "xrf-watch: %s: %s\n", shm_path, strerror(errno));
        return 1;
    }
    struct stat st;
    if (fstat(fd, &st) != 0 || !S_ISREG(st.st_mode) ||
        (size_t)st.st_size < sizeof(struct xrf_shm)) {
        fprintf(stderr, "xrf-watch: %s is not a run's shared memory\n", shm_path);
        close(fd);
        return 1;
    }
    struct xrf_shm *shm =
        mmap(NULL, sizeof(struct xrf_shm), PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
    close(fd);
    if (shm == MAP_FAILED) {
        fprintf(stderr, "xrf-watch: mmap: %s\n", strerror(errno));
        return 1;
    }
    struct xrf_shm_geom g;
    if (xrf_shm_check(shm, sizeof(struct xrf_shm), &g) != 0) {
        fprintf(stderr, "xrf-watch: %s: not a segment of this layout\n", shm_path);
        return 1;
    }

    struct xrf_watch *w = NULL;
    int r = xrf_watch_start(shm, &cfg, &w);
    if (r < 0) {
        fprintf(stderr, "xrf-watch: cannot watch pid %ld: %s\n", loop, strerror(-r));
        return 1;
    }
    /* Ready: the host may stop waiting for us (a line it reads before trusting the backup). */
    printf("{\"watching\": %ld}\n", loop);
    fflush(stdout);
    struct xrf_watch_result res;
    int recorded = -ENOENT;
    if (cfg.notify_fd >= 0) {
        struct pollfd p = {.fd = cfg.notify_fd, .events = POLLIN};
        while (poll(&p, 1, -1) < 0 && errno == EINTR)
            ;
        /* The outputs are safe; for `hold` the arm is being held and lowered meanwhile. */
        if (xrf_watch_result(w, &res) == XRF_WATCH_HOST_GONE)
            recorded = write_record((int)record_fd, record, &res, 0, loop);
    }
    xrf_watch_wait(w, &res);
    if (record_fd >= 0 && res.reason == XRF_WATCH_HOST_GONE)
        recorded = write_record((int)record_fd, record, &res, 1, loop);
    printf("{\"reason\": %d, \"event_ns\": %lld, \"safe_ns\": %lld, \"rest_ns\": %lld, "
           "\"drop_urad\": %d, \"hold_phase\": %d, \"kill_status\": %d, \"hold_status\": %d, "
           "\"hold_channel\": %d, \"record_status\": %d}\n",
           res.reason, (long long)res.event_ns, (long long)res.safe_ns, (long long)res.rest_ns,
           res.drop_urad, res.hold_phase, res.kill_status, res.hold_status, res.hold_channel,
           recorded);
    munmap(shm, sizeof(struct xrf_shm));
    return 0;
}
