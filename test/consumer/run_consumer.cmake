# cmake -P run_consumer.cmake: install lcmx into a unique temporary prefix, build the consumer
# project against it, run its app. The temporary directory is removed on every exit path.
foreach(v LCMX_BUILD_DIR PROJECT_DIR WORK_PARENT GENERATOR CXX_COMPILER)
  if(NOT DEFINED ${v})
    message(FATAL_ERROR "run_consumer.cmake: -D${v}=... is required")
  endif()
endforeach()

string(RANDOM LENGTH 8 ALPHABET 0123456789abcdef tag)
string(TIMESTAMP stamp "%s")
set(work "${WORK_PARENT}/consumer_${stamp}_${tag}")
set(prefix "${work}/prefix")
set(build "${work}/build")
file(MAKE_DIRECTORY "${work}")

# Runs a step; on failure removes the work directory and fails with the step's output.
function(step name)
  execute_process(COMMAND ${ARGN} RESULT_VARIABLE rc OUTPUT_VARIABLE out ERROR_VARIABLE err
                  TIMEOUT 240)
  if(NOT rc EQUAL 0)
    file(REMOVE_RECURSE "${work}")
    message(FATAL_ERROR "consumer test: ${name} failed (${rc})\n--- stdout ---\n${out}\n--- stderr ---\n${err}")
  endif()
  message(STATUS "consumer test: ${name}: ok")
  set(step_output "${out}" PARENT_SCOPE)
endfunction()

step("cmake --install" ${CMAKE_COMMAND} --install "${LCMX_BUILD_DIR}" --prefix "${prefix}")

set(cfg_args -S "${PROJECT_DIR}" -B "${build}" -G "${GENERATOR}"
  "-DCMAKE_PREFIX_PATH=${prefix}" "-DCMAKE_CXX_COMPILER=${CXX_COMPILER}"
  "-DCMAKE_FIND_PACKAGE_NO_PACKAGE_REGISTRY=ON")
if(C_COMPILER)
  list(APPEND cfg_args "-DCMAKE_C_COMPILER=${C_COMPILER}")
endif()
if(BUILD_TYPE)
  list(APPEND cfg_args "-DCMAKE_BUILD_TYPE=${BUILD_TYPE}")
endif()
step("configure the consumer project" ${CMAKE_COMMAND} ${cfg_args})
step("build the consumer project" ${CMAKE_COMMAND} --build "${build}" -j 2)

# The consumer's Runtime joins a discovery group of its own, never LCM's default one.
math(EXPR a "${stamp} % 200 + 20")
math(EXPR b "0x${tag} % 250 + 1")
math(EXPR port "0x${tag} % 20000 + 40000")
# iface=lo: this runs in the root namespace, where no test may join the machine's interface.
set(ENV{LCMX_DISCOVERY_URL} "udpm://239.254.${a}.${b}:${port}?ttl=0&iface=lo")
set(ENV{LCMX_BEACON_PERIOD_MS} "100")
set(ENV{LCMX_LEASE_MS} "600")
step("run the consumer app" "${build}/consumer_app")
if(NOT step_output MATCHES "consumer ok")
  file(REMOVE_RECURSE "${work}")
  message(FATAL_ERROR "consumer app did not say 'consumer ok':\n${step_output}")
endif()
message(STATUS "${step_output}")
# Built only when the installed lcmx has lcmx::dds (LCMX_WITH_DDS).
if(EXISTS "${build}/consumer_dds")
  step("run the consumer's DDS app" "${build}/consumer_dds")
  if(NOT step_output MATCHES "consumer dds ok")
    file(REMOVE_RECURSE "${work}")
    message(FATAL_ERROR "consumer DDS app did not say 'consumer dds ok':\n${step_output}")
  endif()
  message(STATUS "${step_output}")
endif()
file(REMOVE_RECURSE "${work}")
