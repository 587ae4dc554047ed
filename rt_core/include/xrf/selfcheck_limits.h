/*
 * xrf/selfcheck_limits.h — the bench self-check's hard limits, written down here and nowhere
 * else. The checker (rt_core/tools/selfcheck) clamps to them whatever its input says; the bench
 * profile validator (appliance/xrflab/profiles.py, the only one) reads them through the cffi
 * binding (appliance/xrflab/_cffi_build.py), so the two sides cannot disagree.
 *
 * The part between the cffi markers is read by cffi: plain integer #defines only (cffi does not
 * read floating-point macros), hence the duty in per mille.
 */
#ifndef XRF_SELFCHECK_LIMITS_H
#define XRF_SELFCHECK_LIMITS_H

/* cffi-begin */
#define XRF_SC_MAX_DUTY_PERMILLE 200 /* |duty| of a pulse: 20 % of full scale */
#define XRF_SC_MAX_PULSE_MS 200      /* length of one pulse */
#define XRF_SC_MAX_SETTLE_MS 2000    /* zero-PWM wait after a pulse */
#define XRF_SC_MAX_FRAMES 100000     /* echo and timing frames */
#define XRF_SC_MIN_PERIOD_US 200     /* frame period of the timed steps */
#define XRF_SC_MAX_PERIOD_US 20000
/* cffi-end */

#define XRF_SC_MAX_DUTY (XRF_SC_MAX_DUTY_PERMILLE / 1000.0)

#endif /* XRF_SELFCHECK_LIMITS_H */
