// XenoRosDataBridge — XRF2's Ros2Xeno/Xeno2Ros bridge (XenoFrtRosIco::data_bridge). The framework
// takes the newest Ros2Xeno into ros_msg and publishes xeno_msg at the decimated rate every cycle
// (stage 2 of XRF2's order); update() is that stage, already done this cycle.
#pragma once

#include <cstdio>
#include <errno.h>
#include <error.h>
#include <fcntl.h>
#include <stdint.h>
#include <string.h>
#include <sys/sysinfo.h>
#include <sys/types.h>
#include <time.h>
#include <unistd.h>

#include "ICommunication.h"

#ifndef MSEC
#define MSEC 1000000L
#endif
#ifndef SEC
#define SEC 1000000000L
#endif

class XenoRosDataBridge
{
public:
    XenoRosDataBridge() = default;
    // Returns 0: the framework has done this cycle's data exchange.
    int update() { return 0; }
};
