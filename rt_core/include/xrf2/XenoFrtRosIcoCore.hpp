// The message-independent part of XenoFrtRosIco, compiled once into the runtime library. The
// student-facing XenoFrtRosIco (header-only, because the messages are generated per project)
// adds ros_msg and xeno_msg and hands their addresses here.
#pragma once

#include <cstdint>
#include <time.h>

#include "FullStateMachine.hpp"
#include "IcoIo.hpp"
#include "XenoFileHandler.hpp"
#include "XenoFrtLogger.hpp"
#include "XenoFrtLoop.hpp"
#include "XenoFrtMonitor.hpp"
#include "XenoRosCommandBridge.hpp"
#include "XenoRosCommunication.hpp"
#include "XenoRosDataBridge.hpp"
#include "XenoSpiControllerHandler.hpp"
#include "configuration.h"
#include "xrf/channels.h"

namespace xrf
{
class Runtime;
}

class XenoFrtRosIcoCore : public XenoFrtLoop
{
public:
    int step() override;

protected:
    XenoFrtRosIcoCore(unsigned cycle_freq, unsigned write_decimator_freq, unsigned monitor_freq,
                      XenoFileHandler &file, void *log_data);
    void xrfMessages(void *ros_msg, uint32_t ros_size, const char *ros_schema, const void *xeno_msg,
                     uint32_t xeno_size, const char *xeno_schema);
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
    // XRF Lab: a bench of several ico boards (the youBot's 9 channels). Board b (1, 2) is
    // actuate_more[b - 1] / sample_more[b - 1], channels 4b+1 .. 4b+4 as pwm1..4 / channel1..4,
    // exchanged by the framework every cycle like actuate_data / sample_data, and only on a
    // bench that has the board (ico_more[b - 1]). XRF2 projects never see them.
    IcoIo::IcoWrite actuate_more[XRF_MAX_BOARDS - 1]{};
    IcoIo::IcoRead sample_more[XRF_MAX_BOARDS - 1]{};
    static_assert(XRF_MAX_BOARDS == 3, "ico_more names each board beyond board 0");
    IcoIo ico_more[XRF_MAX_BOARDS - 1]{IcoIo(1), IcoIo(2)};
    FullStateMachine state_machine;

    // XRF2's other protected members, for the student code that reads them.
    XenoSpiControllerHandler spi_controller;
    XenoRosCommunication command_com{"XenoCmd"};
    XenoRosCommandBridge command_bridge;
    XenoRosCommunication data_com{"Ros-Xeno"};
    XenoRosDataBridge data_bridge;
    int monitor_freq = 0; // the monitor frequency given to the constructor
    // This cycle's stage timestamps, as XRF2 took them with GET_TIMINGS (filled whatever
    // GET_TIMINGS says, from the timestamps the cycle takes anyway): t1 start of the FPGA
    // exchange, t2 data channel, t3 command channel, t4 monitor, t5 state hook, t6 logger,
    // t7 end of the logger. During a hook t1..t5 are this cycle's, t6 and t7 the last cycle's.
    struct timespec t1 {
    }, t2{}, t3{}, t4{}, t5{}, t6{}, t7{};

private:
    void publishTelemetry(xrf::Runtime &rt, int state);
    void applyCommand(xrf::Runtime &rt);
    void *ros_msg_ = nullptr;
    const void *xeno_msg_ = nullptr;
    uint32_t ros_size_ = 0, xeno_size_ = 0;
    uint32_t ros_seq_ = 0;
    int64_t ros_t_sent_ = 0;
    unsigned decimator_ = 0, decimator_count_ = 0, monitor_freq_ = 0;
    int published_state_ = 0;
    // Boards beyond board 0 on this bench (the transport's), looked up at the first cycle.
    int extra_boards_ = -1;
    int extraBoards(xrf::Runtime &rt);
};
