// `lcmx echo`, `lcmx hz`, `lcmx bw`, `lcmx pub`: looking at and injecting live traffic, with
// run-time types (lcmx::types) and the channel tap (tap.hpp). Registered in main.cpp like
// every verb (verb.hpp).
#pragma once

#include "verb.hpp"

namespace lcmx::cli {

Verb add_echo(CLI::App& app, const Globals& globals);  // echo_cmd.cpp
Verb add_hz(CLI::App& app, const Globals& globals);    // rate_cmd.cpp
Verb add_bw(CLI::App& app, const Globals& globals);    // rate_cmd.cpp
Verb add_pub(CLI::App& app, const Globals& globals);   // pub_cmd.cpp

}  // namespace lcmx::cli
