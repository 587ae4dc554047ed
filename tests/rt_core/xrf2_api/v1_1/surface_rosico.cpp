// XRF2 v1.1's XenoFrtRosIco surface (message members ros_msg / xeno_msg), used the way a
// student controller uses it: every protected member, the eight hooks, the loop's
// protected timing members and getters. Driven to RUN by the test, it also checks what the
// members hold and prints "surface: N failed" at the end (tests/rt_core/xrf2_api/test_xrf2_api.py).
#include "XenoFrtRosIco.hpp"

#include "surface_check.hpp"

#pragma pack(1)
struct Logged {
    double position;
    int counter;
};
#pragma pack(0)

class Surface : public XenoFrtRosIco {
public:
    Surface(uint cycle_time_freq, uint write_decimator_freq, uint monitor_freq)
        : XenoFrtRosIco(cycle_time_freq, write_decimator_freq, monitor_freq, file, &logged),
          file(false, "surface_log", "bin")
    {
        logger.addVariable("position", double_);
        logger.addVariable("counter", integer);
        CHECK(this->monitor_freq == 10);
        CHECK(cycle_time_freq == 500);
    }
    bool runTimeConsistent() const
    {
        return ns(stop_time) > ns(start_time) && ns(run_time) == ns(stop_time) - ns(start_time);
    }
    XenoFileHandler file;
    Logged logged{};
    struct timespec last_wakeup{};
    long long last_missed = 0;
    int cycles_seen = 0;

protected:
    int initialising() override
    {
        CHECK(ico_io.init() == 0);
        CHECK(ico_io.spi_init() == 0);
        CHECK(ico_io.reset() == 0);
        CHECK(ico_io.test() == 0);
        IcoIo::IcoRead rd{};
        CHECK(ico_io.update_io(actuate_data, &rd) == 0);
        CHECK(logger.initialise() == 0);
        CHECK(logger.isInitialised());
        return 1;
    }
    int initialised() override { return 1; }
    int run() override
    {
        if (!logger.isStarted())
            logger.start();
        // The messages: the framework's objects, read and written directly.
        xeno_msg.position = ros_msg.setpoint + sample_data.channel1;
        xeno_msg.counter = ros_msg.counter + 1;
        xeno_msg.state = 4;
        actuate_data.pwm1 = (int16_t)MAX_PWM_VALUE;
        actuate_data.val1 = true;
        actuate_data.pwm2 = 0; actuate_data.val2 = false;
        actuate_data.pwm3 = 0; actuate_data.val3 = false;
        actuate_data.pwm4 = 0; actuate_data.val4 = false;
        const bool pins = sample_data.channel1_1 || sample_data.channel1_2 || sample_data.channel2_1 ||
                          sample_data.channel2_2 || sample_data.channel3_1 || sample_data.channel3_2 ||
                          sample_data.channel4_1 || sample_data.channel4_2;
        (void)pins;
        (void)(sample_data.channel2 + sample_data.channel3 + sample_data.channel4);
        logged.position = xeno_msg.position;
        logged.counter = xeno_msg.counter;
        monitor.update();
        monitor.printf("run %d\n", getCyclesCount());
        checkTiming();
        // The bridge and SPI members.
        Xeno2RosCopy();
        CHECK(command_bridge.update() == 0);
        CHECK(data_bridge.update() == 0);
        command_com.open();
        command_com.close();
        std_msgs::msg::Int32 cmd;
        CHECK(command_com.read(&cmd, sizeof cmd) == 0);
        CHECK(command_com.write(&cmd, sizeof cmd) == (int)sizeof cmd);
        spi_controller.open();
        uint8_t tx[FRAME_SIZE] = {8 /* ENC_1 */}, rx[FRAME_SIZE];
        CHECK(spi_controller.transfer(tx, rx, FRAME_SIZE) == FRAME_SIZE);
        uint8_t pwm_frame[FRAME_SIZE] = {3 /* ALL */};
        CHECK(spi_controller.transfer(pwm_frame, rx, FRAME_SIZE) < 0); // outputs only via ico_io
        CHECK(spi_controller.read(rx, FRAME_SIZE) == FRAME_SIZE);
        CHECK(spi_controller.write(tx, FRAME_SIZE) == FRAME_SIZE);
        spi_controller.close();
        IcoIo::ReadValue in = ico_io.getInput(1);
        CHECK(in.enc < 16384 && in.pin1 <= 1 && in.pin2 <= 1);
        CHECK(ico_io.setOutput(2, 0, false) == 0);
        cycles_seen++;
        return 0;
    }
    int stopping() override
    {
        CHECK(logger.stop() == 0 && !logger.isStarted());
        CHECK(logger.log() == -1); // not started: nothing logged
        return 1;
    }
    int stopped() override { return 0; }
    int pausing() override { return 1; }
    int paused() override { return 0; }
    int error() override { return 0; }

private:
    void Xeno2RosCopy()
    {
        xrf2_msgs::msg::Ros2Xeno in{};
        CHECK(data_com.read(&in, sizeof in) == (int)sizeof in);
        CHECK(in.counter == ros_msg.counter);
        xrf2_msgs::msg::Xeno2Ros out = xeno_msg;
        out.counter = 12345;
        CHECK(data_com.write(&out, sizeof out) == (int)sizeof out);
        CHECK(xeno_msg.counter == 12345);
        xeno_msg.counter = ros_msg.counter + 1;
    }
    void checkTiming()
    {
        // t1..t5 are this cycle's stages, in order, at or after the cycle's deadline.
        CHECK(ns(t1) <= ns(t2) && ns(t2) <= ns(t3) && ns(t3) <= ns(t4) && ns(t4) <= ns(t5));
        CHECK(ns(t1) >= ns(wakeup_time));
        // t6/t7 are last cycle's logger stage: before this cycle began.
        if (cycles_seen > 0)
            CHECK(ns(t6) <= ns(t7) && ns(t7) <= ns(t1));
        // The grid: whole periods (2 ms at 500 Hz) between deadlines, start_time its origin; one
        // period unless the loop overran, and then every period skipped is counted as missed
        // (docs/rt_core/runtime.md, "After an overrun").
        const long long missed = getMissedCycles();
        if (cycles_seen > 0) {
            const long long step = ns(wakeup_time) - ns(last_wakeup);
            CHECK(step >= 2 * MSEC && step % (2 * MSEC) == 0);
            CHECK(step / (2 * MSEC) - 1 <= missed - last_missed);
        }
        CHECK((ns(wakeup_time) - ns(start_time)) % (2 * MSEC) == 0);
        last_wakeup = wakeup_time;
        last_missed = missed;
        // idle_time: when the last cycle's work ended, i.e. before this cycle began.
        struct timespec idle = getIdleTime();
        CHECK(ns(idle) == ns(idle_time));
        if (cycles_seen > 0)
            CHECK(ns(idle_time) <= ns(t1));
        // The same clock as evl_read_clock(EVL_CLOCK_MONOTONIC).
        struct timespec now;
        CHECK(evl_read_clock(EVL_CLOCK_MONOTONIC, &now) == 0);
        CHECK(ns(now) >= ns(t5) && ns(now) - ns(t5) < SEC);
        CHECK(getMissedCycles() >= 0 && getCyclesCount() > 0);
        CHECK(evl_get_self() >= 0);
        (void)stop_time;
        (void)run_time;
    }
};

int run_surface_loop()
{
    Surface s(500, 100, 10);
    const int r = s.loop();
    CHECK(r == 0);
    CHECK(s.cycles_seen > 0);
    // After the loop: stop_time and run_time = stop_time - start_time.
    CHECK(s.runTimeConsistent());
    return r;
}
