#include "Template.hpp"

int main()
{
    // 1 kHz control, the joints to the host at 50 Hz, monitor lines at 2 Hz.
    Template controller(1000, 50, 2);
    return controller.loop();
}
