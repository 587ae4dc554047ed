#include "RelbotController.hpp"

int main()
{
    // 1 kHz control, wheel positions to the host at 50 Hz, monitor lines at 2 Hz.
    RelbotController controller(1000, 50, 2);
    return controller.loop();
}
