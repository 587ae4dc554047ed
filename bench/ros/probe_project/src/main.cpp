// Instrument for the ROS 2 bridge tests and bench/ros/latency.py: 1 kHz loop, Xeno2Ros at
// 100 Hz carrying the cycle number (loss check) and timestamps (latency in both directions).
#include <ctime>

#include "XenoFrtRosIco.hpp"
#include "xrf/runtime.hpp"

namespace {
int64_t monotonicNs()
{
    timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}
} // namespace

class RosProbe : public XenoFrtRosIco {
public:
    RosProbe() : XenoFrtRosIco(1000, 100, 0, file, nullptr), file(false, "logs/ros_probe", "bin") {}

protected:
    int initialising() override { return 1; }
    int initialised() override { report(); return 0; }
    int run() override { report(); return 0; }
    int stopping() override { return 1; }
    int stopped() override { report(); return 0; }
    int paused() override { report(); return 0; }

private:
    void report()
    {
        xrf::Runtime &rt = xrf::Runtime::instance();
        if (ros_msg.t_sent_ns != 0 && ros_msg.t_sent_ns != xeno_msg.echo_t_sent_ns[0]) {
            // A new Ros2Xeno: remember it (newest first); the sample carries the last four, so
            // none is hidden by the decimation even when two arrive between samples.
            for (int i = 3; i > 0; i--) {
                xeno_msg.echo_t_sent_ns[i] = xeno_msg.echo_t_sent_ns[i - 1];
                xeno_msg.t_seen_ns[i] = xeno_msg.t_seen_ns[i - 1];
                xeno_msg.t_written_ns[i] = xeno_msg.t_written_ns[i - 1];
            }
            xeno_msg.echo_t_sent_ns[0] = ros_msg.t_sent_ns;
            xeno_msg.t_seen_ns[0] = monotonicNs();
            // The host's write time of the message this cycle read (the data channel's t_sent).
            xeno_msg.t_written_ns[0] = __atomic_load_n(&rt.shm()->ros2xeno.t_sent_ns, __ATOMIC_ACQUIRE);
            xeno_msg.msgs_seen++;
        }
        // This hook runs after the cycle's telemetry went out: the sample is published by the
        // next cycle, scheduled one period after this one's start.
        const int64_t period = 1000000000LL / (int64_t)rt.effectiveFrequency(getCycleFrequency());
        xeno_msg.cycle = (int64_t)getCyclesCount();
        xeno_msg.t_publish_ns = rt.cycleStart() + period;
    }

    XenoFileHandler file;
};

int main()
{
    static RosProbe probe;
    return probe.loop() == 0 ? 0 : 1;
}
