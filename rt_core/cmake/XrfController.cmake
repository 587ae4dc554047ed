# xrf_add_controller(): one call turns a student project into a controller executable.
#
#   xrf_add_controller(<target>
#                      SOURCES <file>...
#                      [INCLUDE_DIRS <dir>...]
#                      [MSG_DIR <dir>]          # default: msg (Ros2Xeno.msg, Xeno2Ros.msg)
#                      [TWENTY_SIM <dir>])      # a 20-sim generated C++ folder (e.g. controller)
#
# - Generates xrf2_msgs/msg/ros2_xeno.hpp and xeno2_ros.hpp from the two .msg files with the
#   installed msgdef.py: once at configure time (so a bad .msg stops the configure with its
#   file:line message, before any compiler runs) and again as a build step that depends on the
#   .msg files (so editing a .msg and rebuilding regenerates).
# - TWENTY_SIM adds the generated model (minus test_*.cpp, which has its own main()) and its
#   common/ folder, and defines TIME_STEP_SIZE, XRF_20SIM_SUBMODEL and XRF_20SIM_HEADER from
#   <dir>/<Submodel>_tokens.xml; XenoFrt20Sim derives its cycle frequency from TIME_STEP_SIZE.
# - Links XrfRt::xrf_rt, compiles with -O2.
# - Records what it built in <build>/xrf_controllers/<target>.json; the appliance's build.py
#   reads it to find the executable and to report which files were taken.
#
# The variable XRF_MSG_DIR (e.g. -DXRF_MSG_DIR=/path on the cmake command line) overrides
# MSG_DIR: whoever drives the build (the appliance) may supply the messages from elsewhere.

include_guard(GLOBAL)

if(NOT TARGET Python3::Interpreter)
  find_package(Python3 COMPONENTS Interpreter REQUIRED)
endif()

# Reads the value of the token with exactly this name attribute from 20-sim's tokens XML.
# Sets <out_var> to the value (CDATA unwrapped, whitespace trimmed) or to "" when absent.
# A regex cannot anchor on "the same <token> element" reliably, so we locate the exact
# name="..." attribute, then cut at the next </token>.
function(_xrf_20sim_token content name out_var)
  set(value "")
  string(REGEX MATCH "<token[ \t\r\n]+([^>]*[ \t\r\n])?name[ \t\r\n]*=[ \t\r\n]*[\"']${name}[\"'][^>]*>"
         open_tag "${content}")
  if(open_tag)
    string(FIND "${content}" "${open_tag}" start)
    string(LENGTH "${open_tag}" tag_len)
    math(EXPR start "${start} + ${tag_len}")
    string(SUBSTRING "${content}" ${start} -1 rest)
    string(FIND "${rest}" "</token>" stop)
    if(stop GREATER_EQUAL 0)
      string(SUBSTRING "${rest}" 0 ${stop} value)
      string(STRIP "${value}" value)
      if(value MATCHES "^<!\\[CDATA\\[(.*)\\]\\]>$")
        set(value "${CMAKE_MATCH_1}")
      endif()
      string(STRIP "${value}" value)
    endif()
  endif()
  set(${out_var} "${value}" PARENT_SCOPE)
endfunction()

function(xrf_add_controller target)
  cmake_parse_arguments(PARSE_ARGV 1 XAC "" "MSG_DIR;TWENTY_SIM" "SOURCES;INCLUDE_DIRS")
  if(XAC_UNPARSED_ARGUMENTS)
    message(FATAL_ERROR "xrf_add_controller(${target}): unexpected arguments: ${XAC_UNPARSED_ARGUMENTS}")
  endif()
  if(NOT XAC_SOURCES)
    message(FATAL_ERROR "xrf_add_controller(${target}): no SOURCES given")
  endif()

  # ---- messages --------------------------------------------------------------------------
  if(XRF_MSG_DIR)
    set(msg_dir "${XRF_MSG_DIR}")
  elseif(XAC_MSG_DIR)
    set(msg_dir "${XAC_MSG_DIR}")
  else()
    set(msg_dir "msg")
  endif()
  get_filename_component(msg_dir "${msg_dir}" ABSOLUTE BASE_DIR "${CMAKE_CURRENT_SOURCE_DIR}")
  if(NOT IS_DIRECTORY "${msg_dir}")
    message(FATAL_ERROR "xrf_add_controller(${target}): message folder ${msg_dir} not found; "
                        "it must hold Ros2Xeno.msg and Xeno2Ros.msg")
  endif()
  set(msg_files "${msg_dir}/Ros2Xeno.msg" "${msg_dir}/Xeno2Ros.msg")
  foreach(f IN LISTS msg_files)
    if(NOT EXISTS "${f}")
      message(FATAL_ERROR "${f}: file not found (xrf_add_controller(${target}) needs Ros2Xeno.msg and Xeno2Ros.msg in ${msg_dir})")
    endif()
  endforeach()

  # One generated-header folder per target, so two controllers with different messages can
  # live in one build tree.
  set(gen_dir "${CMAKE_CURRENT_BINARY_DIR}/${target}_xrf2_msgs")
  set(gen_headers "${gen_dir}/xrf2_msgs/msg/ros2_xeno.hpp" "${gen_dir}/xrf2_msgs/msg/xeno2_ros.hpp"
                  "${gen_dir}/xrf2_msgs/msg/standard_types.hpp")
  set(gen_cmd "${Python3_EXECUTABLE}" "${XRF_RT_MSGDEF}" --msg-dir "${msg_dir}" --out "${gen_dir}")
  execute_process(COMMAND ${gen_cmd}
                  RESULT_VARIABLE rc OUTPUT_VARIABLE out ERROR_VARIABLE err)
  if(NOT rc EQUAL 0)
    string(STRIP "${err}\n${out}" text)
    message(FATAL_ERROR "${text}\nxrf_add_controller(${target}): the message files in ${msg_dir} are not valid")
  endif()
  foreach(h IN LISTS gen_headers)
    if(NOT EXISTS "${h}")
      message(FATAL_ERROR "xrf_add_controller(${target}): ${XRF_RT_MSGDEF} did not write ${h}")
    endif()
  endforeach()
  # A stamp as the primary output: msgdef.py may leave unchanged headers untouched, and an
  # output older than its inputs would make the rule run on every build.
  set(gen_stamp "${gen_dir}/msgs.stamp")
  add_custom_command(OUTPUT "${gen_stamp}"
    BYPRODUCTS ${gen_headers}
    COMMAND ${gen_cmd}
    COMMAND "${CMAKE_COMMAND}" -E touch "${gen_stamp}"
    DEPENDS ${msg_files} "${XRF_RT_MSGDEF}"
    COMMENT "Generating xrf2_msgs headers for ${target} from ${msg_dir}"
    VERBATIM)

  # ---- sources -------------------------------------------------------------------------
  set(sources "")
  foreach(s IN LISTS XAC_SOURCES)
    get_filename_component(s "${s}" ABSOLUTE BASE_DIR "${CMAKE_CURRENT_SOURCE_DIR}")
    list(APPEND sources "${s}")
  endforeach()
  set(include_dirs "")
  foreach(d IN LISTS XAC_INCLUDE_DIRS)
    get_filename_component(d "${d}" ABSOLUTE BASE_DIR "${CMAKE_CURRENT_SOURCE_DIR}")
    list(APPEND include_dirs "${d}")
  endforeach()
  set(left_out "")
  set(ts_json "null")
  set(defs "")
  set(generated_sources "")
  set(link_opts "")

  # ---- 20-sim --------------------------------------------------------------------------
  if(XAC_TWENTY_SIM)
    get_filename_component(ts_dir "${XAC_TWENTY_SIM}" ABSOLUTE BASE_DIR "${CMAKE_CURRENT_SOURCE_DIR}")
    if(NOT IS_DIRECTORY "${ts_dir}")
      message(FATAL_ERROR "xrf_add_controller(${target}): TWENTY_SIM folder ${ts_dir} not found")
    endif()
    file(GLOB tokens_files "${ts_dir}/*_tokens.xml")
    list(LENGTH tokens_files n_tokens)
    if(n_tokens EQUAL 0)
      message(FATAL_ERROR "${ts_dir}/<Submodel>_tokens.xml: file not found (xrf_add_controller(${target}): "
                          "the TWENTY_SIM folder ${ts_dir} has no *_tokens.xml; 20-sim's C++ code generation "
                          "writes it next to <Submodel>.cpp and the cycle frequency comes from its TIME_STEP_SIZE)")
    elseif(n_tokens GREATER 1)
      message(FATAL_ERROR "xrf_add_controller(${target}): TWENTY_SIM folder ${ts_dir} has several *_tokens.xml "
                          "files (${tokens_files}); keep only the generated submodel's")
    endif()
    file(READ "${tokens_files}" tokens_xml)
    _xrf_20sim_token("${tokens_xml}" "TIME_STEP_SIZE" step)
    _xrf_20sim_token("${tokens_xml}" "SUBMODEL_NAME" submodel)
    if(step STREQUAL "")
      message(FATAL_ERROR "${tokens_files}: no TIME_STEP_SIZE token (xrf_add_controller(${target}) "
                          "takes the cycle frequency from it)")
    endif()
    if(submodel STREQUAL "")
      # Old exports lack the token; the file name carries the same name.
      get_filename_component(submodel "${tokens_files}" NAME)
      string(REGEX REPLACE "_tokens\\.xml$" "" submodel "${submodel}")
      message(STATUS "${tokens_files}: no SUBMODEL_NAME token, using ${submodel} from the file name")
    endif()
    if(NOT submodel MATCHES "^[A-Za-z_][A-Za-z0-9_]*$")
      message(FATAL_ERROR "${tokens_files}: SUBMODEL_NAME '${submodel}' is not a C++ class name")
    endif()
    if(NOT EXISTS "${ts_dir}/${submodel}.h")
      message(FATAL_ERROR "${ts_dir}/${submodel}.h: file not found (named by SUBMODEL_NAME in ${tokens_files})")
    endif()
    # CMake has no floating-point math; Python is here anyway and validates the number too.
    execute_process(COMMAND "${Python3_EXECUTABLE}" -c
      "import sys\ns=float(sys.argv[1])\nassert s>0 and s==s and s!=float('inf')\nprint(round(1.0/s, 6))"
      "${step}" RESULT_VARIABLE rc OUTPUT_VARIABLE freq ERROR_QUIET OUTPUT_STRIP_TRAILING_WHITESPACE)
    if(NOT rc EQUAL 0)
      message(FATAL_ERROR "${tokens_files}: TIME_STEP_SIZE '${step}' is not a positive number")
    endif()
    string(REGEX REPLACE "\\.0$" "" freq "${freq}")

    file(GLOB ts_sources CONFIGURE_DEPENDS "${ts_dir}/*.cpp" "${ts_dir}/*.c")
    file(GLOB common_sources CONFIGURE_DEPENDS "${ts_dir}/common/*.cpp" "${ts_dir}/common/*.c")
    foreach(s IN LISTS ts_sources)
      get_filename_component(name "${s}" NAME)
      if(name MATCHES "^test_")
        # 20-sim's stand-alone test program: it has its own main().
        list(APPEND left_out "${s}")
      else()
        list(APPEND sources "${s}")
      endif()
    endforeach()
    list(APPEND sources ${common_sources})
    # Generated files include each other by bare name ("xxtypes.h", "LoopController.h").
    list(APPEND include_dirs "${ts_dir}")
    if(IS_DIRECTORY "${ts_dir}/common")
      list(APPEND include_dirs "${ts_dir}/common")
    endif()
    list(APPEND defs "TIME_STEP_SIZE=${step}" "XRF_20SIM_SUBMODEL=${submodel}"
                     "XRF_20SIM_HEADER=\"${submodel}.h\"")
    # Live tuning (docs/students/tuning.md): the parameters named in the tokens file, as a
    # translation unit that registers them and interposes the submodel base class's constructor
    # (--wrap below), so the runtime finds m_P[] with the student's and 20-sim's files unchanged.
    get_filename_component(tools_dir "${XRF_RT_MSGDEF}" DIRECTORY)
    set(params_cpp "${gen_dir}/xrf_20sim_params.cpp")
    execute_process(COMMAND "${Python3_EXECUTABLE}" "${tools_dir}/twentysim_params.py"
                            --tokens "${tokens_files}" --out "${params_cpp}" --header "${submodel}.h"
                    RESULT_VARIABLE rc OUTPUT_VARIABLE out ERROR_VARIABLE err
                    OUTPUT_STRIP_TRAILING_WHITESPACE)
    if(NOT rc EQUAL 0)
      message(FATAL_ERROR "${err}\nxrf_add_controller(${target}): cannot read the parameters of ${tokens_files}")
    endif()
    if(err)
      message(WARNING "${err}")
    endif()
    list(APPEND generated_sources "${params_cpp}")
    list(APPEND link_opts "-Wl,--wrap=_ZN13Submodel20simC1Ev" "-Wl,--wrap=_ZN13Submodel20simC2Ev")
    set_property(DIRECTORY APPEND PROPERTY CMAKE_CONFIGURE_DEPENDS "${tokens_files}")
    message(STATUS "xrf_add_controller(${target}): 20-sim submodel ${submodel}, ${out}")
    message(STATUS "xrf_add_controller(${target}): 20-sim submodel ${submodel}, "
                   "TIME_STEP_SIZE ${step} s -> cycle frequency ${freq} Hz (from ${tokens_files})")
    set(ts_json "{\"folder\": \"${ts_dir}\", \"tokens_file\": \"${tokens_files}\", \"submodel\": \"${submodel}\", \"time_step_size\": \"${step}\", \"frequency_hz\": ${freq}}")
  endif()

  # ---- the target ----------------------------------------------------------------------
  add_executable(${target} ${sources} ${generated_sources} ${gen_headers} "${gen_stamp}")
  set_source_files_properties(${gen_headers} PROPERTIES GENERATED TRUE HEADER_FILE_ONLY TRUE)
  target_include_directories(${target} PRIVATE ${include_dirs} "${gen_dir}")
  target_compile_definitions(${target} PRIVATE ${defs})
  target_compile_features(${target} PRIVATE cxx_std_17)
  target_compile_options(${target} PRIVATE -O2)
  target_link_libraries(${target} PRIVATE XrfRt::xrf_rt)
  if(link_opts)
    target_link_options(${target} PRIVATE ${link_opts})
  endif()

  # ---- record for build.py -------------------------------------------------------------
  # JSON written by hand: string(JSON) needs CMake 3.19 and this package supports 3.16.
  # (A path containing a double quote or backslash would break it; build.py reports that.)
  set(src_json "")
  foreach(s IN LISTS sources)
    string(APPEND src_json "\"${s}\", ")
  endforeach()
  string(REGEX REPLACE ", $" "" src_json "${src_json}")
  set(lo_json "")
  foreach(s IN LISTS left_out)
    string(APPEND lo_json "\"${s}\", ")
  endforeach()
  string(REGEX REPLACE ", $" "" lo_json "${lo_json}")
  file(GENERATE OUTPUT "${CMAKE_BINARY_DIR}/xrf_controllers/${target}.json" CONTENT
"{\"target\": \"${target}\",
 \"executable\": \"$<TARGET_FILE:${target}>\",
 \"source_dir\": \"${CMAKE_CURRENT_SOURCE_DIR}\",
 \"msg_dir\": \"${msg_dir}\",
 \"sources\": [${src_json}],
 \"left_out_test_programs\": [${lo_json}],
 \"twenty_sim\": ${ts_json}}
")
endfunction()
