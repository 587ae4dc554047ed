#include "StageController.hpp"

int main()
{
    // 1 kHz control, the position to the host at 50 Hz, monitor lines at 2 Hz.
    StageController controller(1000, 50, 2);
    return controller.loop();
}
