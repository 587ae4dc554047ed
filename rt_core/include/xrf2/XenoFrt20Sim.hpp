// XenoFrt20Sim — XenoFrtRosIco whose cycle frequency is 1 / TIME_STEP_SIZE, the step size of the
// 20-sim model (a compile definition taken from <Submodel>_tokens.xml at configure time by
// xrf_add_controller(... TWENTY_SIM <folder>)).
#pragma once

#include "XenoFrtRosIco.hpp"

#ifndef TIME_STEP_SIZE
#error \
    "TIME_STEP_SIZE is not defined: build with xrf_add_controller(<target> ... TWENTY_SIM <controller folder>)"
#endif

#include "xxmodel.h"

class XenoFrt20Sim : public XenoFrtRosIco
{
public:
    static constexpr unsigned modelFrequency()
    {
        return static_cast<unsigned>(1.0 / (TIME_STEP_SIZE) + 0.5);
    }

    XenoFrt20Sim(unsigned write_decimator_freq, unsigned monitor_freq, XenoFileHandler &file,
                 void *log_data)
        : XenoFrtRosIco(modelFrequency(), write_decimator_freq, monitor_freq, file, log_data)
    {
    }

    // 20-sim's Calculate() stops updating its outputs once model time passes the finish time;
    // a controller on a bench runs for as long as the bench does.
    template <class Model> static void runForever(Model &model) { model.SetFinishTime(0.0); }
};
