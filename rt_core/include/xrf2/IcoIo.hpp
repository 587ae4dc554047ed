// IcoIo — XRF2's ico-board FPGA interface over the transport the runtime chose (spidev, EVL
// out-of-band spidev, or the simulated board); frames per xrf/ico.h.
#pragma once

// XRF2's IcoIo.hpp included these; student code relies on them (memset, open/O_RDWR, ioctl,
// sysinfo, error, ...).
#include <cstdint>
#include <cstdio>
#include <errno.h>
#include <error.h>
#include <fcntl.h>
#include <stdint.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <sys/sysinfo.h>
#include <sys/types.h>
#include <time.h>
#include <unistd.h>

#include "ICommunicationFullDuplex.h"
#include "configuration.h"

struct xrf_ico_transport;

// XRF2's macros, same values. (XRF2 took ENABLE_OUTPUT_LIMIT from configuration.h only when
// XenoFrtRosIco.hpp had included it first; here IcoIo.hpp includes it itself, so MAX_PWM_VALUE
// is the same in every file.)
#define FRAME_SIZE 12
#define MILLION 1000000L
#define BILLION 1000000000L
#if ENABLE_OUTPUT_LIMIT
#define MAX_PWM_VALUE (int)(2047 * MAX_PWM_OUTPUT)
#else
#define MAX_PWM_VALUE 2047
#endif

class IcoIo
{
public:
    struct IcoWrite {
        int16_t pwm1;
        bool val1;
        int16_t pwm2;
        bool val2;
        int16_t pwm3;
        bool val3;
        int16_t pwm4;
        bool val4;
    };
    struct IcoRead {
        int channel1, channel2, channel3, channel4;
        bool channel1_1, channel1_2, channel2_1, channel2_2;
        bool channel3_1, channel3_2, channel4_1, channel4_2;
    };
    // One channel as getInput() returns it (XRF2's layout): 14-bit encoder, two input pins.
    struct ReadValue {
        unsigned int enc : 14;
        unsigned int pin1 : 1;
        unsigned int pin2 : 1;
        // XRF Lab's earlier getInput() returned the encoder count as an int; keep that use working.
        operator int() const { return (int)enc; }
    };

    IcoIo() = default;
    // XRF Lab: board b of a bench with several (channels 4b+1 .. 4b+4; xrf/ico.h's xfer_board).
    // XRF2 had one board, IcoIo() is board 0; the framework exchanges boards 1.. itself
    // (XenoFrtRosIcoCore's actuate_more / sample_more), so student code rarely builds one.
    explicit IcoIo(int board) : board_(board) {}
    // XRF2 built IcoIo on its SPI handler; here the runtime's transport is always used.
    explicit IcoIo(ICommunicationFullDuplex &) {}
    // INIT: 0 when the board answers (reply byte 4 == 11), else -ENODEV; a missing board puts
    // the state machine into ERROR at the end of the cycle.
    int init();
    // XRF2 opened the SPI device here; the runtime has opened the transport already.
    int spi_init() { return 0; }
    int reset(); // encoders to zero, outputs off
    int test();  // TEST echo: 0 intact, -EIO when bits came back wrong
    int setOutput(int channel, int16_t value, bool pin);
    // The channel's encoder and pins (all zero when the channel is not 1..4 or the transfer failed).
    ReadValue getInput(int channel);
    int update_io(const IcoWrite &write, IcoRead *read);

    bool boardMissing() const { return missing_; }
    // The framework keeps the outputs off before initialise and in ERROR/QUIT.
    void setOutputsEnabled(bool on) { outputs_enabled_ = on; }
    // What went to the board in the last update_io (after the safety mask and the limit).
    const int16_t *lastPwm() const { return last_pwm_; }
    const uint8_t *lastDout() const { return last_dout_; }

private:
    int xfer(const uint8_t *tx, uint8_t *rx);
    // Looked up once, not per cycle: the runtime opens one transport for the run and its PWM
    // limit comes from the environment at start.
    struct xrf_ico_transport *transport_ = nullptr;
    int16_t pwm_max_ = -1;
    int board_ = 0;
    bool missing_ = false;
    bool outputs_enabled_ = true;
    int16_t last_pwm_[4] = {0, 0, 0, 0};
    uint8_t last_dout_[4] = {0, 0, 0, 0};
};
