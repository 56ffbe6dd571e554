// `lcmx record`, `lcmx play FILE`, `lcmx log info FILE`: LCM event logs (lcmx::eventlog).
// Registered in main.cpp like every verb (verb.hpp).
#pragma once

#include "verb.hpp"

namespace lcmx::cli {

Verb add_record(CLI::App& app, const Globals& globals);  // record_cmd.cpp
Verb add_play(CLI::App& app, const Globals& globals);    // play_cmd.cpp
Verb add_log(CLI::App& app, const Globals& globals);     // log_cmd.cpp (log info)
// `lcmx log export`, added to `log` by add_log() (log_export.cpp); run when it was parsed.
Verb add_log_export(CLI::App& log);

}  // namespace lcmx::cli
