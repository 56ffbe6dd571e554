#pragma once
// lcmx::types — LCM types at run time from `.lcm` files (no lcm-gen, no rebuild). Umbrella.
#include "lcmx/types/schema.hpp"
#include "lcmx/types/value.hpp"
