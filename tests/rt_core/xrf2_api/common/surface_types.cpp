// The other classes and types XRF2's headers declare, used on their own: FullStateMachine with
// its enums, the logger and file handler with VariableTypes / variableInfo / loggerInfo, the
// monitor, IcoIo's structs, the communication interfaces, and XenoFrt20Sim with the 20-sim code.
#include "XenoFrt20Sim.hpp"

#include "FullStateMachine.hpp"
#include "ICommunication.h"
#include "ICommunicationFullDuplex.h"
#include "IcoIo.hpp"
#include "XenoFileHandler.hpp"
#include "XenoFrtLogger.hpp"
#include "XenoFrtLoop.hpp"
#include "XenoFrtMonitor.hpp"
#include "XenoRosCommandBridge.hpp"
#include "XenoRosCommunication.hpp"
#include "XenoRosDataBridge.hpp"
#include "XenoSpiControllerHandler.hpp"
#include "configuration.h"
#include "debug_settings.h"
#include XRF_20SIM_HEADER

#include "surface_check.hpp"

// A 20-sim controller class as XRF2's 20-sim template declares one (constructed by the loop in
// a real project; here its type must be complete).
class Surface20Sim : public XenoFrt20Sim {
public:
    Surface20Sim(uint write_decimator_freq, uint monitor_freq, XenoFileHandler &f, void *data)
        : XenoFrt20Sim(write_decimator_freq, monitor_freq, f, data)
    {
        controller.SetFinishTime(0.0);
    }
    LoopController controller;
    XXDouble u[4] = {0, 0, 0, 0};
    XXDouble y[2] = {0, 0};
};

int check_types()
{
    static_assert(sizeof(Surface20Sim) > sizeof(XenoFrtRosIco), "complete type");
    CHECK(XenoFrt20Sim::modelFrequency() == 1000);
    CHECK(TIME_STEP_SIZE == 0.001);
    COMMANDS c = START_CMD;
    CHECK(c == 2);
    VariableTypes vt = long_int;
    CHECK(vt == 6);

    int hooks_run = 0;
    FullStateMachine::stateFcn hook = [&] { hooks_run++; return 1; };
    FullStateMachine sm(hook, [] { return 0; }, [] { return 0; }, hook, [] { return 0; }, hook,
                        [] { return 0; }, [] { return 0; });
    CHECK(sm.getState() == IDLE_STATE);
    STATE s = sm.getState();
    CHECK(s == IDLE_STATE);
    CHECK(sm.initialise() == 0 && sm.getState() == INITIALISING_STATE);
    CHECK(sm.step() == 0 && sm.getState() == INITIALISED_STATE && hooks_run == 1);
    CHECK(sm.start() == 0 && sm.getState() == RUN_STATE);
    CHECK(sm.pause() == 0 && sm.getState() == PAUSING_STATE);
    sm.step();
    CHECK(sm.getState() == PAUSED_STATE);
    CHECK(sm.stop() == 0 && sm.getState() == STOPPING_STATE);
    sm.step();
    CHECK(sm.getState() == STOPPED_STATE);
    CHECK(sm.reset() == 0 && sm.getState() == INITIALISING_STATE);
    sm.step();
    CHECK(sm.start() == 0 && sm.stop() == 0);
    sm.step();
    CHECK(sm.quit() == 0 && sm.getState() == QUIT_STATE && sm.step() == 1);
    CHECK(sm.getError() == 0);
    const int states[] = {IDLE_STATE, INITIALISING_STATE, INITIALISED_STATE, RUN_STATE, STOPPING_STATE,
                          STOPPED_STATE, PAUSING_STATE, PAUSED_STATE, ERROR_STATE, QUIT_STATE};
    for (int i = 0; i < 10; i++)
        CHECK(states[i] == i + 1);
    const int cmds[] = {INITIALISE_CMD, START_CMD, STOP_CMD, RESET_CMD, PAUSE_CMD, QUIT_CMD};
    for (int i = 0; i < 6; i++)
        CHECK(cmds[i] == i + 1);

    // Logger types: XRF2's enum and the course guide's spelling, the info structs.
    CHECK(boolean == 1 && character == 2 && integer == 3 && float_ == 4 && double_ == 5 && long_int == 6);
    CHECK(id_bool == boolean && id_char == character && id_int == integer && id_float == float_ &&
          id_double == double_ && id_long_int == long_int);
    variableInfo vi{"x", double_};
    loggerInfo li{};
    li.var_info[0] = vi;
    li.number_var = 1;
    CHECK(li.var_info[0].type == double_);

    // IcoIo's structs
    IcoIo::IcoWrite w{};
    w.pwm1 = MAX_PWM_VALUE;
    w.val4 = true;
    IcoIo::IcoRead r{};
    r.channel4 = 16383;
    r.channel4_2 = true;
    IcoIo::ReadValue rv{};
    rv.enc = 16383;
    rv.pin1 = 1;
    rv.pin2 = 0;
    CHECK((int)rv == 16383 && w.pwm1 == 409 && r.channel4_2);

    // The communication interfaces the bridge members implement.
    XenoSpiControllerHandler spi((uint8_t)1, FRAME_SIZE, (uint32_t)31 * MILLION);
    ICommunicationFullDuplex &duplex = spi;
    ICommunication &plain = duplex;
    (void)plain;
    IcoIo own_io(spi);
    (void)own_io;
    XenoRosCommunication com("Ros-Xeno", 8, 8);
    CHECK(std::string(com.name()) == "Ros-Xeno");
    XenoRosCommandBridge cb;
    XenoRosDataBridge db;
    CHECK(cb.update() == 0 && db.update() == 0);

    // Monitor on its own: 1000 Hz loop, 100 Hz monitor -> due every 10th update.
    XenoFrtMonitor mon(1000, 100);
    int due = 0;
    for (int i = 0; i < 100; i++) {
        mon.update();
        due += mon.isDue() ? 1 : 0;
    }
    CHECK(due == 10);
    return 0;
}
