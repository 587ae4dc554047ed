#ifndef TEMPLATE_HPP
#define TEMPLATE_HPP

#include "XenoFrtRosIco.hpp"

// What the logger writes each cycle. Packed, and the field order must match the order of
// logger.addVariable() calls in the constructor.
#pragma pack(push, 1)
struct TemplateLog
{
    int encoder_left = 0;
    int encoder_right = 0;
    double steer_left = 0.0;
    double steer_right = 0.0;
};
#pragma pack(pop)

class Template : public XenoFrtRosIco
{
public:
    Template(unsigned cycle_freq, unsigned write_decimator_freq, unsigned monitor_freq);

protected:
    // The state machine calls exactly one of these per cycle, for the current state.
    // Return 0 to stay in the state, 1 when the state's work is done (go to the next
    // state), a negative number to go to ERROR (the number is reported as the error).
    int initialising() override;
    int initialised() override;
    int run() override;
    int stopping() override;
    int stopped() override;
    int pausing() override;
    int paused() override;
    int error() override;

private:
    // Constructed after the base class, which only keeps a reference to it until the
    // logger is initialised (XRF2's pattern).
    XenoFileHandler file;
    TemplateLog log_data;
};

#endif // TEMPLATE_HPP
