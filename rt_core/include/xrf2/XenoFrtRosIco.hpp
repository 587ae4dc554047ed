// XenoFrtRosIco — the loop with FPGA, host channels, state machine, monitor and logger; students
// derive from it. Order of work in a cycle: FPGA exchange, data channel, command channel,
// monitor, state hook, logger.
#pragma once

#include "XenoFrtRosIcoCore.hpp"
#include "xrf2_msgs/msg/ros2_xeno.hpp"
#include "xrf2_msgs/msg/xeno2_ros.hpp"

class XenoFrtRosIco : public XenoFrtRosIcoCore {
public:
    XenoFrtRosIco(unsigned cycle_freq, unsigned write_decimator_freq, unsigned monitor_freq,
                  XenoFileHandler &file, void *log_data)
        : XenoFrtRosIcoCore(cycle_freq, write_decimator_freq, monitor_freq, file, log_data)
    {
        xrfMessages(&ros_msg, sizeof ros_msg, xrf2_msgs::msg::Ros2Xeno::XRF_SCHEMA, &xeno_msg,
                    sizeof xeno_msg, xrf2_msgs::msg::Xeno2Ros::XRF_SCHEMA);
    }

protected:
    xrf2_msgs::msg::Ros2Xeno ros_msg{};
    xrf2_msgs::msg::Xeno2Ros xeno_msg{};
};
