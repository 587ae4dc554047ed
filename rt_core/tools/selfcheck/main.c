/*
 * xrf-selfcheck — runs the bench self-check (selfcheck.h) and prints one JSON object per line as
 * it goes: {"event":"start",...}, {"event":"progress",...}, {"event":"step",...} per step,
 * {"event":"end",...}. Exit code: 0 every step passed (warnings allowed), 1 some step failed,
 * 2 the check could not run (bad arguments or profile) or was aborted.
 *
 *   xrf-selfcheck [--transport sim|spidev|evl-spidev] [--sim PLANT] [--faults SPEC]
 *                 [--device /dev/spidev0.0] [--speed HZ] [--profile FLAT|-]
 *                 [--profile-file PATH] [--sim-outputs-shm NAME] [--dump-profile]
 *
 * A tool of its own, not part of the runtime library a controller links. The profile comes
 * validated by appliance/xrflab/profiles.py, as flat key=value lines (profile_flat.c) in a file
 * or on stdin ("-"); --profile-file names the JSON file it came from, for the start event.
 * Without --profile the checker's defaults apply. --dump-profile prints the profile as the
 * checker would use it and exits. SIGINT/SIGTERM abort between two frames; the outputs are
 * zeroed in every case.
 */
#define _POSIX_C_SOURCE 200809L

#include <errno.h>
#include <fcntl.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#include "xrf/channels.h"
#include "xrf/plants.h"
#include "xrf/sim.h"
#include "selfcheck.h"

static volatile sig_atomic_t stop_flag;

static void on_signal(int sig)
{
    (void)sig;
    stop_flag = 1;
}

static void usage(FILE *f)
{
    fprintf(f, "usage: xrf-selfcheck [--transport sim|spidev|evl-spidev] [--sim PLANT]\n"
               "                     [--faults SPEC] [--device PATH] [--speed HZ]\n"
               "                     [--profile FLAT|-] [--profile-file PATH]\n"
               "                     [--sim-outputs-shm NAME] [--dump-profile]\n"
               "The profile is the flat key=value form xrflab.profiles writes (`xrf selfcheck`\n"
               "validates a JSON bench profile and hands it over).\n");
}

static void print_error(const char *msg)
{
    char buf[1024];
    printf("{\"event\":\"error\",\"message\":%s}\n",
           xrf_selfcheck_json_string(msg, buf, sizeof buf));
    fflush(stdout);
}

static void on_progress(void *user, const char *id, int channel, const char *text, double frac)
{
    (void)user;
    char buf[1024];
    printf(
        "{\"event\":\"progress\",\"step\":\"%s\",\"channel\":%d,\"fraction\":%.3f,\"text\":%s}\n",
        id, channel, frac, xrf_selfcheck_json_string(text, buf, sizeof buf));
    fflush(stdout);
}

static void on_result(void *user, const struct xrf_selfcheck_result *r)
{
    (void)user;
    char t[256], m[1024], a[1024];
    printf("{\"event\":\"step\",\"id\":\"%s\",\"channel\":%d,\"status\":\"%s\",\"title\":%s,"
           "\"message\":%s,\"action\":%s,\"data\":%s}\n",
           r->id, r->channel, xrf_selfcheck_status_name(r->status),
           xrf_selfcheck_json_string(r->title, t, sizeof t),
           xrf_selfcheck_json_string(r->message, m, sizeof m),
           xrf_selfcheck_json_string(r->action, a, sizeof a), r->data[0] ? r->data : "{}");
    fflush(stdout);
}

/* The flat profile from a file or stdin ("-") on top of the defaults. */
static int read_profile(const char *path, struct xrf_selfcheck_profile *prof, char *err,
                        size_t errlen)
{
    FILE *f = strcmp(path, "-") == 0 ? stdin : fopen(path, "r");
    if (!f) {
        snprintf(err, errlen, "%s: %s", path, strerror(errno));
        return -errno;
    }
    char why[400];
    int r = xrf_selfcheck_profile_read(f, prof, why, sizeof why);
    if (r)
        snprintf(err, errlen, "%s: %s", strcmp(path, "-") == 0 ? "stdin" : path, why);
    if (f != stdin)
        fclose(f);
    return r;
}

static struct xrf_shm *map_shm(const char *name, char *err, size_t errlen)
{
    char path[256];
    if (!name[0] || strchr(name, '/')) {
        snprintf(err, errlen, "bad shared-memory name '%s'", name);
        return NULL;
    }
    snprintf(path, sizeof path, "/%s", name);
    int fd = shm_open(path, O_RDWR, 0);
    if (fd < 0) {
        snprintf(err, errlen, "/dev/shm/%s: %s", name, strerror(errno));
        return NULL;
    }
    struct stat st;
    if (fstat(fd, &st) != 0 || (size_t)st.st_size < sizeof(struct xrf_shm)) {
        snprintf(err, errlen, "/dev/shm/%s: too small for the XRF layout", name);
        close(fd);
        return NULL;
    }
    void *m = mmap(NULL, sizeof(struct xrf_shm), PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
    close(fd);
    if (m == MAP_FAILED) {
        snprintf(err, errlen, "/dev/shm/%s: mmap: %s", name, strerror(errno));
        return NULL;
    }
    return (struct xrf_shm *)m;
}

/* The bench's channel count into prof->channels: the simulated plant's row says it; a real
 * bench has every channel of the boards its transport reaches. Then every channel the profile
 * lists must be one of them (0), else err says which is not (-ERANGE). */
static int bench_fits(const struct xrf_selfcheck_target *tg, const struct xrf_ico_transport *t,
                      struct xrf_selfcheck_profile *prof, char *err, size_t errlen)
{
    int n = (t->xfer_board && t->boards > 1 ? t->boards : 1) * XRF_ICO_CHANNELS;
    if (strcmp(tg->transport, "sim") == 0) {
        int robot = xrf_sim_robot_from_name(tg->sim ? tg->sim : "relbot");
        int plant = robot >= 0 ? xrf_plant_channels(robot) : 0;
        if (plant > 0 && plant < n)
            n = plant;
    }
    if (n > XRF_MAX_CHANNELS)
        n = XRF_MAX_CHANNELS;
    prof->channels = n;
    return xrf_selfcheck_profile_fits(prof, n, err, errlen);
}

int main(int argc, char **argv)
{
    const char *transport = "sim", *sim = NULL, *faults = NULL, *device = NULL, *profile = NULL;
    const char *shm_name = NULL, *profile_file = NULL;
    unsigned long speed = 0;
    int dump = 0;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char **dst = NULL;
        if (strcmp(a, "-h") == 0 || strcmp(a, "--help") == 0) {
            usage(stdout);
            return 0;
        }
        if (strcmp(a, "--dump-profile") == 0) {
            dump = 1;
            continue;
        }
        if (strcmp(a, "--transport") == 0)
            dst = &transport;
        else if (strcmp(a, "--sim") == 0)
            dst = &sim;
        else if (strcmp(a, "--faults") == 0)
            dst = &faults;
        else if (strcmp(a, "--device") == 0)
            dst = &device;
        else if (strcmp(a, "--profile") == 0)
            dst = &profile;
        else if (strcmp(a, "--profile-file") == 0)
            dst = &profile_file;
        else if (strcmp(a, "--sim-outputs-shm") == 0)
            dst = &shm_name;
        else if (strcmp(a, "--speed") == 0 && i + 1 < argc) {
            char *end;
            speed = strtoul(argv[++i], &end, 10);
            if (*end || speed == 0 || speed > 200000000ul) {
                print_error("--speed wants a clock in Hz, e.g. 31000000");
                return 2;
            }
            continue;
        }
        if (!dst || i + 1 >= argc) {
            usage(stderr);
            char msg[256];
            snprintf(msg, sizeof msg, "unknown or incomplete argument '%s'", a);
            print_error(msg);
            return 2;
        }
        *dst = argv[++i];
    }

    char err[512] = "";
    struct xrf_selfcheck_profile prof;
    xrf_selfcheck_profile_defaults(&prof);
    if (profile && read_profile(profile, &prof, err, sizeof err)) {
        print_error(err);
        return 2;
    }
    if (!profile_file)
        profile_file = profile && strcmp(profile, "-") != 0 ? profile : "";
    if (dump) {
        xrf_selfcheck_profile_dump(stdout, &prof);
        return 0;
    }
    /* A profile named after a plant of the table checks that plant's simulated board (relbot,
     * jiwy, stage, ...); an edited profile with a name of its own gets the RELbot's. */
    if (!sim)
        sim = xrf_plant_id(prof.name) > 0 ? prof.name : "relbot";

    struct xrf_shm *shm = NULL;
    if (shm_name) {
        shm = map_shm(shm_name, err, sizeof err);
        if (!shm) {
            print_error(err);
            return 2;
        }
    }

    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal; /* no SA_RESTART: a sleep returns EINTR and the flag is seen */
    sigemptyset(&sa.sa_mask);
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGHUP, &sa, NULL);
    signal(SIGPIPE, SIG_IGN);

    char js[6][600];
    printf("{\"event\":\"start\",\"profile\":%s,\"profile_file\":%s,\"transport\":%s,\"sim\":%s,"
           "\"faults\":%s,\"device\":%s,\"pid\":%d,\"time\":%lld}\n",
           xrf_selfcheck_json_string(prof.name, js[0], sizeof js[0]),
           xrf_selfcheck_json_string(profile_file, js[1], sizeof js[1]),
           xrf_selfcheck_json_string(transport, js[2], sizeof js[2]),
           xrf_selfcheck_json_string(strcmp(transport, "sim") == 0 ? sim : "", js[3], sizeof js[3]),
           xrf_selfcheck_json_string(faults ? faults : "", js[4], sizeof js[4]),
           xrf_selfcheck_json_string(device ? device : "", js[5], sizeof js[5]), (int)getpid(),
           (long long)time(NULL));
    fflush(stdout);

    struct xrf_selfcheck_target tg = {
        .transport = transport,
        .device = device,
        .speed_hz = (uint32_t)speed,
        .sim = sim,
        .faults = faults,
        .sim_outputs = shm ? &shm->sim : NULL,
    };
    struct xrf_ico_transport *t = NULL;
    struct xrf_selfcheck_result r;
    int rc = xrf_selfcheck_open(&tg, &t, &r);
    on_result(NULL, &r);
    struct xrf_selfcheck_summary sum;
    memset(&sum, 0, sizeof sum);
    const char *verdict;
    int exit_code;
    if (rc != 0) {
        if (rc == -EINVAL) {
            print_error(r.message);
            verdict = "error";
            exit_code = 2;
        } else {
            /* The SPI step itself failed: a finding about the bench, not a usage error. */
            sum.failed = 1;
            verdict = "fail";
            exit_code = 1;
        }
    } else if (bench_fits(&tg, t, &prof, err, sizeof err) != 0) {
        /* A channel the bench does not have: refused before anything moves. */
        print_error(err);
        verdict = "error";
        exit_code = 2;
        sum.outputs_zeroed = xrf_selfcheck_zero_outputs(t) == 0;
        t->close(t);
    } else {
        struct xrf_selfcheck_hooks hooks = {on_progress, on_result, NULL, &stop_flag};
        rc = xrf_selfcheck_run(t, &prof, &hooks, &sum);
        sum.passed++; /* the spi step */
        if (rc == -EINTR || stop_flag) {
            verdict = "aborted";
            exit_code = 2;
        } else if (rc < 0) {
            verdict = "error";
            exit_code = 2;
        } else {
            verdict = sum.failed ? "fail" : "pass";
            exit_code = sum.failed ? 1 : 0;
        }
        /* run() zeroed the outputs already; once more costs nothing and covers every path. */
        sum.outputs_zeroed = xrf_selfcheck_zero_outputs(t) == 0 && sum.outputs_zeroed;
        t->close(t);
    }
    printf("{\"event\":\"end\",\"verdict\":\"%s\",\"passed\":%d,\"warned\":%d,\"failed\":%d,"
           "\"skipped\":%d,\"aborted\":%s,\"outputs_zeroed\":%s}\n",
           verdict, sum.passed, sum.warned, sum.failed, sum.skipped, sum.aborted ? "true" : "false",
           sum.outputs_zeroed ? "true" : "false");
    fflush(stdout);
    if (shm)
        munmap(shm, sizeof *shm);
    return exit_code;
}
