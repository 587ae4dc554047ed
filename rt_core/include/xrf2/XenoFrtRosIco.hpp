// XenoFrtRosIco — the loop with FPGA, host channels, state machine, monitor and logger; students
// derive from it. Order of work in a cycle: FPGA exchange, data channel, command channel,
// monitor, state hook, logger.
//
// Both XRF2 releases' names for the messages work: ros_msg / xeno_msg (v1.1) and ros_data /
// xeno_data (the first release) are the same two objects.
#pragma once

#include <functional>

#include "XenoFrtRosIcoCore.hpp"
#include "configuration.h"
#include "xrf2_msgs/msg/ros2_xeno.hpp"
#include "xrf2_msgs/msg/xeno2_ros.hpp"

class XenoFrtRosIco : public XenoFrtRosIcoCore
{
public:
    XenoFrtRosIco(unsigned cycle_freq, unsigned write_decimator_freq, unsigned monitor_freq,
                  XenoFileHandler &file, void *log_data)
        : XenoFrtRosIcoCore(cycle_freq, write_decimator_freq, monitor_freq, file, log_data)
    {
        xrfMessages(&ros_msg, sizeof ros_msg, xrf2_msgs::msg::Ros2Xeno::XRF_SCHEMA, &xeno_msg,
                    sizeof xeno_msg, xrf2_msgs::msg::Xeno2Ros::XRF_SCHEMA);
        data_com.xrfBind(&ros_msg, (int)sizeof ros_msg, &xeno_msg, (int)sizeof xeno_msg);
    }

protected:
    xrf2_msgs::msg::Ros2Xeno ros_msg{};
    xrf2_msgs::msg::Xeno2Ros xeno_msg{};
    // The first XRF2 release's names: references, so both names are the same objects (no copy
    // per cycle, a write through either is seen through the other).
    xrf2_msgs::msg::Ros2Xeno &ros_data{ros_msg};
    xrf2_msgs::msg::Xeno2Ros &xeno_data{xeno_msg};
};
