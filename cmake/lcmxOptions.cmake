# All lcmx build options, in one place.
#
# lcmx_option(NAME "doc" DEFAULT) declares a plain option.
# lcmx_optional_dependency(NAME "doc" PACKAGE...) declares an option for an optional part:
#   unset   -> ON when the dependency is found, OFF (with a status line) otherwise;
#   ON      -> the dependency is REQUIRED (configure fails if it is missing);
#   OFF     -> not built.
macro(lcmx_option name doc default)
  option(${name} "${doc}" ${default})
endmacro()

macro(lcmx_optional_dependency name doc package)
  if(NOT DEFINED ${name})
    find_package(${package} QUIET)
    if(${package}_FOUND)
      set(${name} ON CACHE BOOL "${doc}")
    else()
      set(${name} OFF CACHE BOOL "${doc}")
      message(STATUS "lcmx: ${package} not found, ${name}=OFF")
    endif()
  elseif(${name})
    find_package(${package} REQUIRED)
  endif()
endmacro()

lcmx_option(LCMX_BUILD_TESTS "Build the Catch2 test suite" ${LCMX_IS_TOP})
lcmx_option(LCMX_BUILD_BENCH "Build the benchmarks under bench/" ${LCMX_IS_TOP})
lcmx_option(LCMX_BUILD_APPS "Build the lcmx tool, daemons and examples" ${LCMX_IS_TOP})
lcmx_option(LCMX_BUILD_FUZZERS "Build the libFuzzer targets under test/fuzz (needs clang++)" ${LCMX_BUILD_TESTS})
lcmx_option(LCMX_SANITIZE_ADDRESS "Build with AddressSanitizer and UBSan (scripts/sanitizers.sh address)" OFF)
lcmx_option(LCMX_SANITIZE_THREAD "Build with ThreadSanitizer (scripts/tsan.sh)" OFF)
lcmx_option(LCMX_WARNINGS_AS_ERRORS "Treat compiler warnings as errors" OFF)

if(LCMX_SANITIZE_ADDRESS AND LCMX_SANITIZE_THREAD)
  message(FATAL_ERROR "LCMX_SANITIZE_ADDRESS and LCMX_SANITIZE_THREAD cannot be combined")
endif()
# Any UBSan finding aborts the process (and fails its test) instead of printing and going on.
if(LCMX_SANITIZE_ADDRESS)
  # -Wno-maybe-uninitialized: g++ 12's instrumentation makes it fire inside libstdc++ (std::regex's
  # std::function members, in apps/lcmx); the plain build keeps the warning.
  add_compile_options(-fsanitize=address,undefined -fno-sanitize-recover=undefined -fno-omit-frame-pointer
                      -Wno-maybe-uninitialized)
  add_link_options(-fsanitize=address,undefined -fno-sanitize-recover=undefined)
endif()
if(LCMX_SANITIZE_THREAD)
  add_compile_options(-fsanitize=thread -fno-omit-frame-pointer)
  add_link_options(-fsanitize=thread)
endif()

# Warnings for lcmx's own targets: lcmx_target_warnings(target)
function(lcmx_target_warnings target)
  target_compile_options(${target} PRIVATE -Wall -Wextra -Wpedantic)
  if(LCMX_WARNINGS_AS_ERRORS)
    target_compile_options(${target} PRIVATE -Werror)
  endif()
endfunction()

# The Python module (python/): ON when pybind11 and Python's headers are found. The interpreter
# is Debian's /usr/bin/python3 unless Python3_EXECUTABLE says otherwise (not a pyenv shim on
# PATH: the module must match the interpreter that runs it).
if(NOT DEFINED Python3_EXECUTABLE AND EXISTS /usr/bin/python3)
  set(Python3_EXECUTABLE /usr/bin/python3 CACHE FILEPATH "Python interpreter of the lcmx module")
endif()
# Sanitized builds leave it out by default: the interpreter is not sanitized (the ASan runtime
# must come first) and it would report Python's own allocations as leaks.
if(NOT DEFINED LCMX_WITH_PYTHON AND (LCMX_SANITIZE_ADDRESS OR LCMX_SANITIZE_THREAD))
  set(LCMX_WITH_PYTHON OFF CACHE BOOL "Build the Python module (pybind11)")
  message(STATUS "lcmx: sanitized build, LCMX_WITH_PYTHON=OFF")
endif()
if(NOT DEFINED LCMX_WITH_PYTHON OR LCMX_WITH_PYTHON)
  find_package(Python3 COMPONENTS Interpreter Development.Module QUIET)
endif()
if(NOT DEFINED LCMX_WITH_PYTHON AND NOT Python3_FOUND)
  set(LCMX_WITH_PYTHON OFF CACHE BOOL "Build the Python module (pybind11)")
  message(STATUS "lcmx: Python 3 headers not found, LCMX_WITH_PYTHON=OFF")
endif()
lcmx_optional_dependency(LCMX_WITH_PYTHON "Build the Python module (pybind11)" pybind11)

# The Cyclone DDS gateway (dds/, `lcmx dds-gateway`, `lcmx idl`): ON when Cyclone DDS's C API
# (Debian: cyclonedds-dev) and its IDL compiler idlc (cyclonedds-tools) are found; ON forces
# both (REQUIRED); OFF leaves dds/ out, and nothing else of lcmx links Cyclone.
# ThreadSanitizer builds leave it out by default: Cyclone is not instrumented, and its threads
# call the gateway's listeners (TSan would report its own blind spots as races).
if(NOT DEFINED LCMX_WITH_DDS AND LCMX_SANITIZE_THREAD)
  set(LCMX_WITH_DDS OFF CACHE BOOL "Build the Cyclone DDS gateway (dds/)")
  message(STATUS "lcmx: ThreadSanitizer build, LCMX_WITH_DDS=OFF")
endif()
if(NOT DEFINED LCMX_WITH_DDS)
  find_package(CycloneDDS QUIET)
  find_program(LCMX_IDLC_EXECUTABLE idlc)
  if(CycloneDDS_FOUND AND LCMX_IDLC_EXECUTABLE)
    set(LCMX_WITH_DDS ON CACHE BOOL "Build the Cyclone DDS gateway (dds/)")
  else()
    set(LCMX_WITH_DDS OFF CACHE BOOL "Build the Cyclone DDS gateway (dds/)")
    message(STATUS "lcmx: Cyclone DDS (cyclonedds-dev) or idlc (cyclonedds-tools) not found, LCMX_WITH_DDS=OFF")
  endif()
elseif(LCMX_WITH_DDS)
  find_package(CycloneDDS REQUIRED)
  find_program(LCMX_IDLC_EXECUTABLE idlc REQUIRED)
endif()
