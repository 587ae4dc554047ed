// XenoRosCommunication — XRF2's cross-buffer between the loop and the ROS side
// (XenoFrtRosIco::command_com and data_com). XRF Lab's loop talks to the host through its
// shared-memory channels, which the framework serves once per cycle in XRF2's order; these
// objects give student code that used the members the same data:
//   data_com.read()  copies the Ros2Xeno the framework took this cycle (ros_msg),
//   data_com.write() copies into Xeno2Ros (xeno_msg), published at the decimated rate,
//   command_com.read() returns 0 (the framework applies commands itself, as XRF2's did),
//   command_com.write() returns the size (the framework publishes the state).
#pragma once

#include "ICommunication.h"
#include "debug_settings.h"
#include "xrf_evl_compat.h"

class XenoRosCommunication : public ICommunication
{
public:
    // name: XRF2's cross-buffer name ("XenoCmd"/"Control" for commands, "Ros-Xeno" for data).
    explicit XenoRosCommunication(const char *name, int linux_xeno_buffer_size = 0,
                                  int xeno_linux_buffer_size = 0)
        : name_(name)
    {
        (void)linux_xeno_buffer_size;
        (void)xeno_linux_buffer_size;
    }
    void open() override {}
    void close() override {}
    int read(void *rx_data, int data_size) override;
    int write(const void *tx_data, int data_size) override;

    const char *name() const { return name_; }
    // Set by the framework: where the message this channel carries lives (nullptr: commands).
    void xrfBind(void *in, int in_size, void *out, int out_size)
    {
        in_ = in;
        in_size_ = in_size;
        out_ = out;
        out_size_ = out_size;
    }

private:
    const char *name_;
    void *in_ = nullptr;
    int in_size_ = 0;
    void *out_ = nullptr;
    int out_size_ = 0;
};
