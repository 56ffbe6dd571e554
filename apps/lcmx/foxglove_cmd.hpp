// `lcmx foxglove` (foxglove_cmd.cpp): the Foxglove WebSocket server daemon (lcmx::foxglove,
// docs/foxglove.md). Registered in main.cpp like every verb (verb.hpp).
#pragma once

#include "verb.hpp"

namespace lcmx::cli {

Verb add_foxglove(CLI::App& app, const Globals& globals);

}  // namespace lcmx::cli
