# lcmx_generate_types(TARGET <name> FILES a.lcm b.lcm ... [OUTPUT_DIR <dir>])
#
# Runs lcm-gen --cpp on the given .lcm files at build time and makes <name> an INTERFACE
# library whose include directory holds the generated headers (<package>/<type>.hpp).
# Link it: target_link_libraries(app PRIVATE <name> lcmx::core).
# The generated files live in the build tree; nothing is written to the source tree.
include_guard(GLOBAL)
include(${CMAKE_CURRENT_LIST_DIR}/lcmxFindLcm.cmake)

function(lcmx_generate_types)
  cmake_parse_arguments(ARG "" "TARGET;OUTPUT_DIR" "FILES" ${ARGN})
  if(NOT ARG_TARGET)
    message(FATAL_ERROR "lcmx_generate_types: TARGET is required")
  endif()
  if(NOT ARG_FILES)
    message(FATAL_ERROR "lcmx_generate_types(${ARG_TARGET}): FILES is empty")
  endif()
  if(NOT ARG_OUTPUT_DIR)
    set(ARG_OUTPUT_DIR ${CMAKE_CURRENT_BINARY_DIR}/${ARG_TARGET}_lcmgen)
  endif()

  set(outputs)
  foreach(lcm_file IN LISTS ARG_FILES)
    get_filename_component(abs ${lcm_file} ABSOLUTE)
    if(NOT EXISTS ${abs})
      message(FATAL_ERROR "lcmx_generate_types(${ARG_TARGET}): no such file ${abs}")
    endif()
    # lcm-gen's output names come from the file's contents: package and struct names.
    # (file(STRINGS) splits lines at ';', so match without it.)
    file(STRINGS ${abs} pkg_line REGEX "^[ \t]*package[ \t]+[A-Za-z0-9_.]+")
    set(pkg_dir "")
    if(pkg_line)
      list(GET pkg_line 0 pkg_line)
      string(REGEX REPLACE "^[ \t]*package[ \t]+([A-Za-z0-9_.]+).*" "\\1" pkg "${pkg_line}")
      string(REPLACE "." "/" pkg_dir "${pkg}")
      set(pkg_dir "${pkg_dir}/")
    endif()
    file(STRINGS ${abs} struct_lines REGEX "^[ \t]*struct[ \t]+[A-Za-z0-9_]+")
    set(file_outputs)
    foreach(line IN LISTS struct_lines)
      string(REGEX REPLACE "^[ \t]*struct[ \t]+([A-Za-z0-9_]+).*" "\\1" type "${line}")
      list(APPEND file_outputs ${ARG_OUTPUT_DIR}/${pkg_dir}${type}.hpp)
    endforeach()
    if(NOT file_outputs)
      message(FATAL_ERROR "lcmx_generate_types(${ARG_TARGET}): no struct found in ${abs}")
    endif()
    add_custom_command(
      OUTPUT ${file_outputs}
      COMMAND ${CMAKE_COMMAND} -E make_directory ${ARG_OUTPUT_DIR}
      COMMAND ${LCM_GEN_EXECUTABLE} --cpp --cpp-hpath ${ARG_OUTPUT_DIR} --cpp-std c++11 ${abs}
      DEPENDS ${abs}
      COMMENT "lcm-gen ${lcm_file}"
      VERBATIM)
    list(APPEND outputs ${file_outputs})
  endforeach()

  add_custom_target(${ARG_TARGET}_gen DEPENDS ${outputs})
  add_library(${ARG_TARGET} INTERFACE)
  add_dependencies(${ARG_TARGET} ${ARG_TARGET}_gen)
  # SYSTEM: lcm-gen's code does not build cleanly under -Wpedantic; that is not ours to fix.
  target_include_directories(${ARG_TARGET} SYSTEM INTERFACE $<BUILD_INTERFACE:${ARG_OUTPUT_DIR}>)
  target_link_libraries(${ARG_TARGET} INTERFACE lcmx::lcm_coretypes)
  set_property(TARGET ${ARG_TARGET} PROPERTY LCMX_GENERATED_DIR ${ARG_OUTPUT_DIR})
endfunction()
