// The API-surface program: the header/macro, libevl and type checks, then the release's
// controller on the loop until the test quits it.
#include "XenoFrtRosIco.hpp"

#include "surface_check.hpp"

int surface_failures = 0;

int main()
{
    if (evl_init())
        error(1, errno, "evl_init()");
    check_headers();
    check_evl();
    check_types();
    run_surface_loop();
    std::printf("surface: %d failed\n", surface_failures);
    return surface_failures == 0 ? 0 : 1;
}
