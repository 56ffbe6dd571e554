# Finds LCM (Debian's liblcm-dev + liblcm-bin) without pkg-config: Debian's lcm.pc
# requires glib's .pc, which lcmx does not otherwise need.
#
# Defines:
#   lcmx::lcm            imported target: lcm headers + liblcm (C library)
#   lcmx::lcm_coretypes  imported interface target: headers only (what lcm-gen C++ code needs)
#   LCM_GEN_EXECUTABLE   path to lcm-gen
include_guard(GLOBAL)

find_path(LCM_INCLUDE_DIR lcm/lcm_coretypes.h)
find_library(LCM_LIBRARY NAMES lcm)
find_program(LCM_GEN_EXECUTABLE lcm-gen)

if(NOT LCM_INCLUDE_DIR OR NOT LCM_LIBRARY OR NOT LCM_GEN_EXECUTABLE)
  message(FATAL_ERROR
    "lcmx needs LCM: headers (${LCM_INCLUDE_DIR}), library (${LCM_LIBRARY}) and lcm-gen "
    "(${LCM_GEN_EXECUTABLE}). On Debian: apt-get install liblcm-dev liblcm-bin "
    "(or run scripts/setup.sh).")
endif()

if(NOT TARGET lcmx::lcm)
  add_library(lcmx::lcm UNKNOWN IMPORTED)
  set_target_properties(lcmx::lcm PROPERTIES
    IMPORTED_LOCATION "${LCM_LIBRARY}"
    INTERFACE_INCLUDE_DIRECTORIES "${LCM_INCLUDE_DIR}")
endif()
if(NOT TARGET lcmx::lcm_coretypes)
  add_library(lcmx::lcm_coretypes INTERFACE IMPORTED)
  set_target_properties(lcmx::lcm_coretypes PROPERTIES
    INTERFACE_INCLUDE_DIRECTORIES "${LCM_INCLUDE_DIR}")
endif()
