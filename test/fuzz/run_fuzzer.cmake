# CTest driver of one libFuzzer target (cmake -P). Never writes into the source tree.
#   -DFUZZER=<binary> -DWORK=<scratch dir, wiped> -DSEEDS=<dir> -DREGRESSIONS=<dir>
#   [-DCORPUS=<committed seeds>] [-DGENERATED_REGRESSIONS=<dir>] -DMAX_TIME=<s> -DMAX_LEN=<bytes>
# Missing CORPUS/SEEDS/REGRESSIONS directories are fine (no inputs).
# The environment variable LCMX_FUZZ_SECONDS, when set, replaces MAX_TIME (capped at 540 s, below
# the test's timeout).
# Copies the seeds and the kept reproducers into WORK/corpus (libFuzzer adds to its first corpus
# directory), runs every one of them first, then fuzzes until MAX_TIME seconds have passed in all.
# Fails when the fuzzer reports a crash, a leak, a timeout or out-of-memory; the input is left in
# WORK.
foreach(var FUZZER WORK SEEDS REGRESSIONS MAX_TIME MAX_LEN)
  if(NOT DEFINED ${var})
    message(FATAL_ERROR "run_fuzzer.cmake: -D${var}=... is required")
  endif()
endforeach()

if(DEFINED ENV{LCMX_FUZZ_SECONDS})
  set(MAX_TIME "$ENV{LCMX_FUZZ_SECONDS}")
endif()
if(NOT MAX_TIME MATCHES "^[0-9]+$" OR MAX_TIME LESS 1)
  message(FATAL_ERROR "run_fuzzer.cmake: LCMX_FUZZ_SECONDS / MAX_TIME must be a whole number of seconds >= 1, got '${MAX_TIME}'")
endif()
if(MAX_TIME GREATER 540)
  set(MAX_TIME 540)
endif()

file(REMOVE_RECURSE "${WORK}")
file(MAKE_DIRECTORY "${WORK}/corpus" "${WORK}/artifacts")
foreach(dir IN ITEMS "${CORPUS}" "${SEEDS}" "${REGRESSIONS}" "${GENERATED_REGRESSIONS}")
  if(IS_DIRECTORY "${dir}")
    file(GLOB inputs LIST_DIRECTORIES false "${dir}/*")
    list(FILTER inputs EXCLUDE REGEX "/README[^/]*$")
    if(inputs)
      file(COPY ${inputs} DESTINATION "${WORK}/corpus")
    endif()
  endif()
endforeach()

execute_process(
  COMMAND "${FUZZER}"
    -max_total_time=${MAX_TIME} -rss_limit_mb=1024 -timeout=5 -max_len=${MAX_LEN}
    -print_final_stats=1 -artifact_prefix=${WORK}/artifacts/
    "${WORK}/corpus"
  WORKING_DIRECTORY "${WORK}"
  RESULT_VARIABLE rc)

if(NOT rc EQUAL 0)
  file(GLOB artifacts "${WORK}/artifacts/*")
  get_filename_component(name "${FUZZER}" NAME)
  message(FATAL_ERROR
    "${name} failed (exit ${rc}). Input(s): ${artifacts}\n"
    "Reproduce: ${FUZZER} <input>. Keep a real bug's input under test/fuzz/regressions/.")
endif()
