/*
 * xrf/plants.h — the simulated plants the sim board can drive, as its one plant table
 * (rt_core/src/plants.c) lists them. Everything else that names a plant (XRF_SIM, the CLI's
 * --sim, the appliance's API and pages, the self-check) asks here, through the cffi binding from
 * Python, so adding a plant is a plant file and a row in that table (docs/developers/adding-a-robot.md).
 *
 * The part between the cffi markers is read by appliance/xrflab/_cffi_build.py: plain integer
 * #defines, fixed-width fields, prototypes.
 */
#ifndef XRF_PLANTS_H
#define XRF_PLANTS_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* cffi-begin */
#define XRF_PLANT_NAME_MAX 16
#define XRF_PLANT_TITLE_MAX 64
#define XRF_PLANT_STATE_TEXT 160

/* What a plant is, for hosts: names and sizes, no behaviour. */
struct xrf_plant_info {
    int32_t id;        /* what xrf_sim_open() takes: the plant's position in the table, from 1 */
    int32_t axes;      /* motor channels wired, 1..axes (PWM n drives the motor behind encoder n) */
    int32_t state_len; /* values xrf_sim_plant_state() gives and the board mirrors (<= 8) */
    int32_t channels;  /* the bench's channel count the plant's row declares (>= axes) */
    char name[XRF_PLANT_NAME_MAX];    /* XRF_SIM=<name>, lower case */
    char title[XRF_PLANT_TITLE_MAX];  /* for people */
    char state[XRF_PLANT_STATE_TEXT]; /* the state's names and units, comma-separated */
};

/* Number of plants in the table; their ids are 1..count. */
int xrf_plant_count(void);
/* The plant with this id into *out: 0, or -EINVAL for an unknown id or a NULL out. */
int xrf_plant_describe(int id, struct xrf_plant_info *out);
/* The channel count row `id` declares (1..XRF_MAX_CHANNELS: the bench the plant stands on),
 * or 0 for no such row. */
int xrf_plant_channels(int id);
/* The id of a plant by name (case-insensitive), or -EINVAL. */
int xrf_plant_id(const char *name);
/* "relbot, jiwy, ..." into buf (for messages); returns the length it needed, like snprintf. */
int xrf_plant_names(char *buf, size_t size);
/* cffi-end */

#ifdef __cplusplus
}
#endif

#endif /* XRF_PLANTS_H */
