// `lcmx services` and `lcmx call`: services seen by discovery, and calls with JSON typed by the
// `.lcm` files of the type path (service_cmd.cpp). Registered in main.cpp like every verb.
#pragma once

#include "verb.hpp"

namespace lcmx::cli {

Verb add_services(CLI::App& app, const Globals& globals);
Verb add_call(CLI::App& app, const Globals& globals);

}  // namespace lcmx::cli
