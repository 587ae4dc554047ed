// XenoRosCommandBridge — XRF2's command/state bridge (XenoFrtRosIco::command_bridge). The
// framework applies one command and publishes the state every cycle (stage 3 of XRF2's order);
// update() is that stage, already done this cycle, so calling it again changes nothing.
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

// XRF2 included ROS 2's std_msgs Int32 here (the XenoCmd / XenoState message).
#include <std_msgs/msg/int32.hpp>

#include "FullStateMachine.hpp"
#include "ICommunication.h"
#include "debug_settings.h"
#include "xrf_evl_compat.h"

#ifndef MSEC
#define MSEC 1000000L
#endif
#ifndef SEC
#define SEC 1000000000L
#endif

class XenoRosCommandBridge
{
public:
    XenoRosCommandBridge() = default;
    // Returns 0: the framework has done this cycle's command exchange.
    int update() { return 0; }
};
