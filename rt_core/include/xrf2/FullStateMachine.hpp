// FullStateMachine — XRF2's coordination state machine. The command table is the one of
// channels.h (xrf_cmd_transition), shared with every host.
#pragma once

#include <functional>

#include "debug_settings.h"
#include "xrf/channels.h"

// XRF2's names for the states and commands (IDLE_STATE, START_CMD, ...), made from the one list
// of each in channels.h, so they carry the same numbers.
#define XRF2_STATE_ENUM_(NAME, number) NAME##_STATE = number,
#define XRF2_CMD_ENUM_(NAME, name, number, safe) NAME##_CMD = number,
enum STATE { XRF_STATES(XRF2_STATE_ENUM_) };
enum COMMANDS { XRF_CMDS(XRF2_CMD_ENUM_) };

class FullStateMachine
{
public:
    using Hook = std::function<int()>;
    using stateFcn = Hook; // XRF2's name for it
    FullStateMachine(Hook initialising, Hook initialised, Hook run, Hook stopping, Hook stopped,
                     Hook pausing, Hook paused, Hook error);

    // Runs the current state's hook: 0 stays, 1 completes the state, < 0 goes to ERROR.
    // Returns 1 only in QUIT. Inline, the usual "stay" answer without a further call (the loop
    // runs it every cycle); what a hook's other answers do is settle() (xrf2_state_machine.cpp).
    int step()
    {
        if (state_ == QUIT_STATE)
            return 1;
        if (state_ == IDLE_STATE)
            return 0;
        Hook &hook = hooks_[state_ - INITIALISING_STATE];
        const int r = hook ? hook() : 0;
        if (r != 0)
            settle(r);
        return 0;
    }

    // Commands return 0 when accepted, or -1 (unknown) / -2 (not allowed in this state).
    int initialise() { return command(INITIALISE_CMD); }
    int start() { return command(START_CMD); }
    int stop() { return command(STOP_CMD); }
    int reset() { return command(RESET_CMD); }
    int pause() { return command(PAUSE_CMD); }
    int quit() { return command(QUIT_CMD); }
    int command(int cmd);
    // Goes to ERROR with `error` as the last error (used by the framework, e.g. no FPGA).
    void fail(int error);

    STATE getState() const { return static_cast<STATE>(state_); }
    int getError() const { return error_; }

private:
    void settle(int r); // a hook's answer other than 0

    Hook hooks_[8];
    int state_ = IDLE_STATE;
    int error_ = 0;
};
