# lcmx_generate_dds_types(TARGET <name> FILES a.lcm ... [ROS2] [NAME <base>] [OUTPUT_DIR <dir>])
#
# For DDS programs that exchange typed messages with `lcmx dds-gateway` (docs/dds.md "Typed
# mode"): runs `lcmx idl` on the .lcm files (every type in them, ROS2: ROS 2 naming) into
# <dir>/<base>.idl, then Cyclone's idlc into <base>.c/<base>.h, and makes <name> a static C
# library of them (include <base>.h; links CycloneDDS::ddsc). Needs LCMX_WITH_DDS (idlc, Cyclone)
# and the lcmx tool: the lcmx_cli target of this build, else `lcmx` on the PATH.
include_guard(GLOBAL)

function(lcmx_generate_dds_types)
  cmake_parse_arguments(ARG "ROS2" "TARGET;NAME;OUTPUT_DIR" "FILES" ${ARGN})
  if(NOT ARG_TARGET OR NOT ARG_FILES)
    message(FATAL_ERROR "lcmx_generate_dds_types: TARGET and FILES are required")
  endif()
  if(NOT ARG_NAME)
    set(ARG_NAME ${ARG_TARGET})
  endif()
  if(NOT ARG_OUTPUT_DIR)
    set(ARG_OUTPUT_DIR ${CMAKE_CURRENT_BINARY_DIR}/${ARG_TARGET}_idl)
  endif()
  if(NOT LCMX_IDLC_EXECUTABLE)
    find_program(LCMX_IDLC_EXECUTABLE idlc REQUIRED)
  endif()
  if(TARGET lcmx_cli)
    set(tool $<TARGET_FILE:lcmx_cli>)
    set(tool_dep lcmx_cli)
  else()
    # An installed lcmx: its prefix's bin/ (this file is in <prefix>/lib*/cmake/lcmx), else PATH.
    find_program(LCMX_TOOL_EXECUTABLE lcmx HINTS ${CMAKE_CURRENT_FUNCTION_LIST_DIR}/../../../bin REQUIRED)
    set(tool ${LCMX_TOOL_EXECUTABLE})
    set(tool_dep)
  endif()
  set(files)
  foreach(f IN LISTS ARG_FILES)
    get_filename_component(abs ${f} ABSOLUTE)
    list(APPEND files ${abs})
  endforeach()
  set(ros2)
  if(ARG_ROS2)
    set(ros2 --ros2)
  endif()
  set(idl ${ARG_OUTPUT_DIR}/${ARG_NAME}.idl)
  add_custom_command(
    OUTPUT ${idl}
    COMMAND ${CMAKE_COMMAND} -E make_directory ${ARG_OUTPUT_DIR}
    COMMAND ${tool} idl ${files} ${ros2} -o ${idl}
    DEPENDS ${tool_dep} ${files}
    COMMENT "lcmx idl -> ${ARG_NAME}.idl"
    VERBATIM)
  add_custom_command(
    OUTPUT ${ARG_OUTPUT_DIR}/${ARG_NAME}.c ${ARG_OUTPUT_DIR}/${ARG_NAME}.h
    COMMAND ${LCMX_IDLC_EXECUTABLE} -o ${ARG_OUTPUT_DIR} ${idl}
    DEPENDS ${idl}
    COMMENT "idlc ${ARG_NAME}.idl"
    VERBATIM)
  add_library(${ARG_TARGET} STATIC ${ARG_OUTPUT_DIR}/${ARG_NAME}.c)
  target_include_directories(${ARG_TARGET} PUBLIC $<BUILD_INTERFACE:${ARG_OUTPUT_DIR}>)
  target_link_libraries(${ARG_TARGET} PUBLIC CycloneDDS::ddsc)
endfunction()
