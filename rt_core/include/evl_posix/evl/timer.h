/* <evl/timer.h> for builds without libevl: everything is declared in <evl/evl.h> (see there). */
#include "evl.h"
