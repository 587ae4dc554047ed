// debug_settings.h — XRF2's per-file debug switches (XenoFrtLoop.hpp and others included it, so
// student code can test them). They are all off and switch nothing on in XRF Lab: its own
// diagnostics are the monitor, the timing histograms and XRF_LOG_TIMING.
#pragma once

#ifndef DEBUG_X_BUF
#define DEBUG_X_BUF 0
#endif
#ifndef DEBUG_SPI
#define DEBUG_SPI 0
#endif
#ifndef DEBUG_LOOP
#define DEBUG_LOOP 0
#endif
#ifndef CONTROL_BRIDGE_DEBUG
#define CONTROL_BRIDGE_DEBUG 0
#endif
#ifndef ROS_BRIDGE_DEBUG
#define ROS_BRIDGE_DEBUG 0
#endif
#ifndef STATE_MACHINE_DEBUG
#define STATE_MACHINE_DEBUG 0
#endif
#ifndef FILE_HANDLER_DEBUG
#define FILE_HANDLER_DEBUG 0
#endif
#ifndef LOGGER_DEBUG
#define LOGGER_DEBUG 0
#endif
