// IcoIo — XRF2's ico-board FPGA interface over the transport the runtime chose (spidev, EVL
// out-of-band spidev, or the simulated board); frames per xrf/ico.h.
#pragma once

#include <cstdint>

class IcoIo {
public:
    struct IcoWrite {
        int16_t pwm1; bool val1;
        int16_t pwm2; bool val2;
        int16_t pwm3; bool val3;
        int16_t pwm4; bool val4;
    };
    struct IcoRead {
        int channel1, channel2, channel3, channel4;
        bool channel1_1, channel1_2, channel2_1, channel2_2;
        bool channel3_1, channel3_2, channel4_1, channel4_2;
    };

    IcoIo() = default;
    // INIT: 0 when the board answers (reply byte 4 == 11), else -ENODEV; a missing board puts
    // the state machine into ERROR at the end of the cycle.
    int init();
    int reset();   // encoders to zero, outputs off
    int test();    // TEST echo: 0 intact, -EIO when bits came back wrong
    int setOutput(int channel, int16_t value, bool pin);
    int getInput(int channel);
    int update_io(const IcoWrite &write, IcoRead *read);

    bool boardMissing() const { return missing_; }
    // The framework keeps the outputs off before initialise and in ERROR/QUIT.
    void setOutputsEnabled(bool on) { outputs_enabled_ = on; }
    // What went to the board in the last update_io (after the safety mask and the limit).
    const int16_t *lastPwm() const { return last_pwm_; }
    const uint8_t *lastDout() const { return last_dout_; }

private:
    int xfer(const uint8_t *tx, uint8_t *rx);
    bool missing_ = false;
    bool outputs_enabled_ = true;
    int16_t last_pwm_[4] = {0, 0, 0, 0};
    uint8_t last_dout_[4] = {0, 0, 0, 0};
};
