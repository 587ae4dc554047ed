// The controller's tunable parameters as the runtime keeps them: what XRF_TUNABLEs and a 20-sim
// export registered before loop(), published into the run's parameter block (xrf/params.h) at
// enter(), and the loop's side of a set. Internal to the runtime.
#pragma once

#include <cstdint>

#include "xrf/params.h"

namespace xrf
{
namespace params
{

// enter(): fills the table of p (before ready); prints each registration it had to leave out
// unless quiet. Not real-time.
void publish(xrf_params *p, bool quiet);
// The loop's side of one pending set (a cycle boundary, before the hook): copy, check, apply
// all or nothing, answer. Bounded, no allocation, no system call.
void take(xrf_params *p, uint32_t *seen, uint64_t cycle);
// After the controller's initialising() completed: 20-sim's Initialize() wrote the generated
// defaults into m_P[]; the values set so far are written again. Bounded.
void afterInitialise();

} // namespace params
} // namespace xrf
