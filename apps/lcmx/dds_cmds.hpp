// `lcmx dds-gateway ...` and `lcmx idl` (dds_cmd.cpp; built with LCMX_WITH_DDS only, docs/dds.md).
#pragma once

#include "verb.hpp"

namespace lcmx::cli {

// `lcmx dds-gateway --config FILE [--check] | status`. Exit codes: 0 ok, 1 runtime failure
// (e.g. Cyclone refused the interface), 2 bad config or usage.
Verb add_dds_gateway(CLI::App& app, const Globals& globals);
// `lcmx idl [--type NAME]... [--ros2] [-o FILE] PATH...`: IDL for .lcm types. 0 ok, 2 bad input.
Verb add_idl(CLI::App& app, const Globals& globals);

}  // namespace lcmx::cli
