// The message-independent part of XenoFrtRosIco, compiled once into the runtime library. The
// student-facing XenoFrtRosIco (header-only, because the messages are generated per project)
// adds ros_msg and xeno_msg and hands their addresses here.
#pragma once

#include <cstdint>

#include "FullStateMachine.hpp"
#include "IcoIo.hpp"
#include "XenoFileHandler.hpp"
#include "XenoFrtLogger.hpp"
#include "XenoFrtLoop.hpp"
#include "XenoFrtMonitor.hpp"

class XenoFrtRosIcoCore : public XenoFrtLoop {
public:
    int step() override;

protected:
    XenoFrtRosIcoCore(unsigned cycle_freq, unsigned write_decimator_freq, unsigned monitor_freq,
                      XenoFileHandler &file, void *log_data);
    void xrfMessages(void *ros_msg, uint32_t ros_size, const char *ros_schema,
                     const void *xeno_msg, uint32_t xeno_size, const char *xeno_schema);
    void xrfAfterLastCycle() override;

    // State hooks and their XRF2 defaults.
    virtual int initialising() { return 1; }
    virtual int initialised() { return 0; }
    virtual int run() { return 1; }
    virtual int stopping() { return 1; }
    virtual int stopped() { return 0; }
    virtual int pausing() { return 1; }
    virtual int paused() { return 0; }
    virtual int error() { return 0; }

    IcoIo::IcoWrite actuate_data{};
    IcoIo::IcoRead sample_data{};
    XenoFrtMonitor monitor;
    XenoFrtLogger logger;
    IcoIo ico_io;
    FullStateMachine state_machine;

private:
    void publishTelemetry(int state);
    void applyCommand();
    void *ros_msg_ = nullptr;
    const void *xeno_msg_ = nullptr;
    uint32_t ros_size_ = 0, xeno_size_ = 0;
    uint32_t ros_seq_ = 0;
    int64_t ros_t_sent_ = 0;
    unsigned decimator_ = 0, decimator_count_ = 0, monitor_freq_ = 0;
    int published_state_ = 0;
};
