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
 *   xrf-watch --shm PATH|--shm-fd FD --loop PID --host PID [--reaction zero|brake|hold] [--plant NAME]
 *             [--brake-channel N] [--spi DEVICE] [--rt-priority N]
 */
#define _GNU_SOURCE

#include <errno.h>
#include <signal.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include "xrf/channels.h"
#include "xrf/plants.h"
#include "xrf/watch.h"

static int usage(const char *why)
{
    fprintf(stderr,
            "xrf-watch: %s\nusage: xrf-watch --shm PATH --loop PID --host PID [--reaction NAME] "
            "[--plant NAME] [--brake-channel N] [--spi DEVICE] [--rt-priority N]\n",
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

int main(int argc, char **argv)
{
    long shm_fd = -1;
    const char *shm_path = NULL, *reaction = "zero", *plant = NULL, *spi = "";
    long loop = 0, host = 0, brake = 0, prio = 0;
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
        else
            return usage("unknown option or bad value");
    }
    /* Our stdout may be a pipe to the host that is gone: the report must not kill us. */
    signal(SIGPIPE, SIG_IGN);
    if ((shm_path == NULL) == (shm_fd < 0) || loop == 0 || host == 0)
        return usage("--shm or --shm-fd, --loop and --host are needed");
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
    cfg.notify_fd = -1;
    cfg.check_ns = 20000000;
    if (strlen(spi) >= sizeof cfg.spi_device)
        return usage("--spi path too long");
    memcpy(cfg.spi_device, spi, strlen(spi) + 1);
    cfg.spi_speed_hz = 31000000;
    cfg.force_sim = spi[0] == '\0';
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
    xrf_watch_wait(w, &res);
    printf("{\"reason\": %d, \"event_ns\": %lld, \"safe_ns\": %lld, \"rest_ns\": %lld, "
           "\"drop_urad\": %d, \"hold_phase\": %d, \"kill_status\": %d, \"hold_status\": %d}\n",
           res.reason, (long long)res.event_ns, (long long)res.safe_ns, (long long)res.rest_ns,
           res.drop_urad, res.hold_phase, res.kill_status, res.hold_status);
    munmap(shm, sizeof(struct xrf_shm));
    return 0;
}
