// The runtime puts the loop thread in real-time mode and reads its options (XRF_*) from the
// environment; an XRF2-style main with evl_init/mlockall/pthread works as well.
#include "ControlLoop.hpp"

int main()
{
    // The cycle frequency comes from the 20-sim model (1 / TIME_STEP_SIZE).
    // Xeno2Ros to the host at 100 Hz, monitor.printf at 2 Hz.
    ControlLoop controller(100, 2);
    return controller.loop();
}
