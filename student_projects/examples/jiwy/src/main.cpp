#include "JiwyController.hpp"

int main()
{
    // 1 kHz control, camera angles to the host at 50 Hz, monitor lines at 2 Hz.
    JiwyController controller(1000, 50, 2);
    return controller.loop();
}
