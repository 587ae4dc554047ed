// What XRF2's XenoFrtRosIco.hpp made visible: its macros with their values, and the C/C++
// headers it included, used here without including anything else.
#include "XenoFrtRosIco.hpp"

#include "surface_check.hpp"

static_assert(MAX_PWM_VALUE == 409, "XRF2's default limit: (int)(2047 * 0.2)");
static_assert(ENABLE_OUTPUT_LIMIT == 1, "XRF2's configuration.h");
static_assert(GET_TIMINGS == 1, "XRF2's configuration.h");
static_assert(FRAME_SIZE == 12, "IcoIo.hpp");
static_assert(MILLION == 1000000L && BILLION == 1000000000L, "IcoIo.hpp");
static_assert(MSEC == 1000000L && SEC == 1000000000L, "XenoFrtLoop.hpp");
static_assert(DEBUG_LOOP == 0 && DEBUG_SPI == 0 && DEBUG_X_BUF == 0 && CONTROL_BRIDGE_DEBUG == 0 &&
                  ROS_BRIDGE_DEBUG == 0 && STATE_MACHINE_DEBUG == 0 && FILE_HANDLER_DEBUG == 0 &&
                  LOGGER_DEBUG == 0,
              "debug_settings.h");

int check_headers()
{
    CHECK(MAX_PWM_OUTPUT > 0.19 && MAX_PWM_OUTPUT < 0.21);
    // <cstring>: memset, strcpy, strlen
    char buf[32];
    memset(buf, 0, sizeof buf);
    strcpy(buf, "xrf2");
    CHECK(strlen(buf) == 4);
    // <fcntl.h>, <unistd.h>: open, O_RDWR, close
    int fd = open("/dev/null", O_RDWR);
    CHECK(fd >= 0);
    // <sys/ioctl.h>: ioctl (FIONREAD on /dev/null fails or answers; the call must compile)
    int pending = 0;
    (void)ioctl(fd, FIONREAD, &pending);
    close(fd);
    // <sys/sysinfo.h>
    struct sysinfo si;
    CHECK(sysinfo(&si) == 0);
    // <sys/stat.h>
    struct stat st;
    CHECK(stat("/", &st) == 0 && S_ISDIR(st.st_mode));
    // <cassert>
    assert(si.uptime >= 0);
    // <filesystem>
    std::filesystem::path p = std::filesystem::path("/tmp") / "x";
    CHECK(p.filename() == "x");
    // <memory>, <vector>, <string>, <functional>
    std::shared_ptr<int> sp = std::make_shared<int>(3);
    std::unique_ptr<int> up(new int(4));
    std::vector<std::string> v{"a", "b"};
    std::function<int()> f = [&] { return *sp + *up + (int)v.size(); };
    CHECK(f() == 9);
    // std_msgs::msg::Int32, as XRF2's command bridge made it visible
    std_msgs::msg::Int32 cmd;
    cmd.data = 2;
    std_msgs::msg::Int32::SharedPtr shared = std::make_shared<std_msgs::msg::Int32>(cmd);
    CHECK(shared->data == 2 && *shared == cmd);
    // uint, error(), mlockall(), pthreads, sched, errno
    uint u = 1;
    CHECK(u == 1);
    CHECK(mlockall(MCL_CURRENT) == 0 || errno == EPERM || errno == ENOMEM);
    pthread_t self = pthread_self();
    CHECK(pthread_equal(self, pthread_self()));
    cpu_set_t cpus;
    CPU_ZERO(&cpus);
    CPU_SET(0, &cpus);
    CHECK(CPU_ISSET(0, &cpus));
    struct sched_param param;
    param.sched_priority = 1;
    (void)param;
    (void)SCHED_FIFO;
    (void)PTHREAD_EXPLICIT_SCHED;
    if (false)
        error(1, errno, "never");
    // <time.h>
    struct timespec ts;
    CHECK(clock_gettime(CLOCK_MONOTONIC, &ts) == 0);
    // <cstdio>, <stdarg.h>
    std::printf("surface: headers checked\n");
    return 0;
}
