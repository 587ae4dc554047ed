// FullStateMachine over the shared command table.
#include "FullStateMachine.hpp"

#include <utility>

#include "params_registry.h"
#include "xrf/channels.h"

FullStateMachine::FullStateMachine(Hook initialising, Hook initialised, Hook run, Hook stopping,
                                   Hook stopped, Hook pausing, Hook paused, Hook error)
    : hooks_{std::move(initialising), std::move(initialised), std::move(run),
             std::move(stopping),     std::move(stopped),     std::move(pausing),
             std::move(paused),       std::move(error)}
{
}

int FullStateMachine::command(int cmd)
{
    int32_t next = xrf_cmd_transition(state_, cmd);
    if (next < 0)
        return next == -XRF_REJECT_UNKNOWN ? -1 : -2;
    state_ = next;
    return 0;
}

void FullStateMachine::fail(int error)
{
    error_ = error;
    state_ = ERROR_STATE;
}

void FullStateMachine::settle(int r)
{
    if (r < 0) {
        fail(r);
        return;
    }
    if (r == 1) {
        // 20-sim's Initialize() (in initialising()) wrote the generated defaults into m_P[]:
        // the values tuned so far, or saved with the project, hold again from here.
        if (state_ == INITIALISING_STATE)
            xrf::params::afterInitialise();
        // The completion table of channels.h, which the dashboard draws too.
        const int32_t next = xrf_state_complete(state_);
        if (next > 0)
            state_ = next;
    }
}
