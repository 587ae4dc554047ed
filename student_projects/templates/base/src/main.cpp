// The short main the runtime allows: the runtime itself puts the loop thread in real-time
// mode (SCHED_FIFO or EVL), locks memory and reads its options (XRF_*) from the environment,
// so nothing else is needed here. An XRF2-style main (evl_init, mlockall, a pthread with
// SCHED_FIFO priority 1 on CPU 1) works as well.
#include "Template.hpp"

int main()
{
    // 1000 Hz loop, Xeno2Ros sent to the host at 100 Hz, monitor.printf at 2 Hz.
    Template controller(1000, 100, 2);
    return controller.loop();
}
