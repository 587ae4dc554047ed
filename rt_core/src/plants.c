/*
 * plants.c — the plant table: every plant the simulated board can drive, one row each. A row
 * names the `const struct xrf_plant_ops xrf_plant_<name>` its plant file (plant_<name>.c)
 * defines; a plant's id is its position here, from 1 (XRF_SIM_RELBOT, XRF_SIM_JIWY in sim.h keep
 * their numbers: append new rows). Everything else that lists plants asks this table: the sim
 * board (sim_board.c), XRF_SIM in the runtime, and through the cffi binding the CLI, the
 * appliance's API and pages and the 3D view (appliance/xrflab/plants.py).
 */
#include <errno.h>
#include <stdio.h>
#include <string.h>
#include <strings.h>

#include "plant.h"
#include "xrf/plants.h"

#define XRF_PLANT_TABLE(ROW) \
    ROW(relbot)              \
    ROW(jiwy)                \
    ROW(stage)               \
    ROW(cell)                \
    ROW(youbot)

#define XRF_PLANT_DECLARE(n) extern const struct xrf_plant_ops xrf_plant_##n;
XRF_PLANT_TABLE(XRF_PLANT_DECLARE)

#define XRF_PLANT_ROW(n) &xrf_plant_##n,
static const struct xrf_plant_ops *const table[] = {XRF_PLANT_TABLE(XRF_PLANT_ROW)};

#define XRF_PLANT_N ((int)(sizeof table / sizeof table[0]))

const struct xrf_plant_ops *xrf_plant_ops(int id)
{
    return (id >= 1 && id <= XRF_PLANT_N) ? table[id - 1] : NULL;
}

int xrf_plant_count(void)
{
    return XRF_PLANT_N;
}

static void copy_text(char *dst, size_t size, const char *src)
{
    snprintf(dst, size, "%s", src ? src : "");
}

int xrf_plant_describe(int id, struct xrf_plant_info *out)
{
    const struct xrf_plant_ops *p = xrf_plant_ops(id);
    if (!p || !out)
        return -EINVAL;
    memset(out, 0, sizeof *out);
    out->id = id;
    out->axes = p->axes;
    out->state_len = p->state_len;
    copy_text(out->name, sizeof out->name, p->name);
    copy_text(out->title, sizeof out->title, p->title);
    copy_text(out->state, sizeof out->state, p->state_names);
    return 0;
}

int xrf_plant_id(const char *name)
{
    if (!name)
        return -EINVAL;
    for (int i = 0; i < XRF_PLANT_N; i++)
        if (strcasecmp(name, table[i]->name) == 0)
            return i + 1;
    return -EINVAL;
}

int xrf_plant_names(char *buf, size_t size)
{
    int need = 0;
    for (int i = 0; i < XRF_PLANT_N; i++) {
        size_t at = (size_t)need < size ? (size_t)need : size;
        int n = snprintf(buf ? buf + at : NULL, buf ? size - at : 0, "%s%s", i ? ", " : "",
                         table[i]->name);
        if (n < 0)
            return -EINVAL;
        need += n;
    }
    if (XRF_PLANT_N == 0 && buf && size)
        buf[0] = '\0';
    return need;
}
