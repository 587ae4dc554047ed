// configuration.h — XRF2's framework settings, under XRF2's names and with XRF2's values, for the
// student code that reads them (XenoFrtRosIco.hpp includes this file, as XRF2's did). Each may be
// overridden with a compile definition. On XRF Lab the limit the board actually gets is the
// runtime's (XRF_PWM_LIMIT, default 0.2 = these values); MAX_PWM_VALUE (IcoIo.hpp) is the
// compile-time figure XRF2 students scale and clamp with.
#pragma once

// XRF2: "1" made XenoFrtRosIco time every stage of the cycle into its members t1..t7. XRF Lab
// always fills them (from the stage timestamps the loop takes anyway), whatever this says.
#ifndef GET_TIMINGS
#define GET_TIMINGS 1
#endif

// XRF2: limit the PWM output to MAX_PWM_OUTPUT of full scale.
#ifndef ENABLE_OUTPUT_LIMIT
#define ENABLE_OUTPUT_LIMIT 1
#endif
// XRF2: the largest PWM output allowed, as a fraction of full scale (0 to 1).
#ifndef MAX_PWM_OUTPUT
#define MAX_PWM_OUTPUT 0.2
#endif
