// `lcmx monitor` (monitor_cmd.cpp, model in monitor_model.hpp) and `lcmx graph` (graph_cmd.cpp,
// model in graph_model.hpp). Registered in main.cpp like every verb (verb.hpp).
#pragma once

#include "verb.hpp"

namespace lcmx::cli {

Verb add_monitor(CLI::App& app, const Globals& globals);  // monitor_cmd.cpp
Verb add_graph(CLI::App& app, const Globals& globals);    // graph_cmd.cpp

}  // namespace lcmx::cli
