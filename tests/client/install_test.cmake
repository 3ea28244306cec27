# ctest client_install: installs the kdrt_client component (library, headers, CMake package, the
# kdrt binary) into a temp prefix, checks that no installed header declares an engine function or
# includes a header that is not installed, then configures, builds and runs tests/client/consumer,
# which uses find_package(kdrt), links kdrt::client and compiles every installed header.
#   cmake -DBUILD_DIR=... -DCONSUMER_DIR=... -DWORK_DIR=... -DGENERATOR=... -DCXX_COMPILER=...
#         -DSANITIZE=ON|OFF -P install_test.cmake

include(${CMAKE_CURRENT_LIST_DIR}/../common/run_command.cmake)

set(prefix ${WORK_DIR}/prefix)
file(REMOVE_RECURSE ${WORK_DIR})
run(${CMAKE_COMMAND} --install ${BUILD_DIR} --prefix ${prefix} --component kdrt_client)

file(GLOB_RECURSE config ${prefix}/*/kdrtConfig.cmake)
if(NOT config)
    message(FATAL_ERROR "no kdrtConfig.cmake under ${prefix}")
endif()
file(GLOB_RECURSE targets ${prefix}/*/kdrtTargets*.cmake)
foreach(file IN LISTS targets)
    file(READ ${file} text)
    if(text MATCHES "OpenImageIO|kdrt_engine[^_]|TBB::")
        message(FATAL_ERROR "${file} makes kdrt::client depend on OpenImageIO, kdrt_engine or TBB")
    endif()
endforeach()
if(EXISTS ${prefix}/include/kdrt/proto/image_io.h)
    message(FATAL_ERROR "image_io.h (OpenImageIO) was installed")
endif()

# The installed headers are value types and the functions of the installed libraries only: none
# may declare an engine function (kdrt_engine is not installed, so a call would not link), and
# every kdrt header they include must be installed too. Comments are dropped before matching
# (they may name engine functions).
set(engine_functions "build_kdtree|compute_stats|validate_mesh|mesh_bounds|default_camera|"
    "validate_render_settings|render_camera_rays|generate_rays|intersect_block|occluded_block|"
    "intersect_single|occluded_single|serialize_tree|deserialize_tree|"
    "Image[ \t\n]+render[ \t\n]*\\(|class[ \t\n]+Camera[ \t\n]*{")
string(CONCAT engine_functions ${engine_functions})
file(GLOB_RECURSE headers RELATIVE ${prefix}/include ${prefix}/include/*.h)
if(NOT headers)
    message(FATAL_ERROR "no headers under ${prefix}/include")
endif()
set(all_headers "")
foreach(header IN LISTS headers)
    file(READ ${prefix}/include/${header} text)
    string(REGEX REPLACE "//[^\n]*" "" code "${text}")
    if(code MATCHES "(${engine_functions})")
        message(FATAL_ERROR "${header} declares an engine function (${CMAKE_MATCH_1}); the installed "
                            "package does not link kdrt_engine")
    endif()
    string(REGEX MATCHALL "#include[ \t]+[\"<]kdrt/[^\">]+[\">]" includes "${code}")
    foreach(include IN LISTS includes)
        string(REGEX REPLACE "#include[ \t]+[\"<]([^\">]+)[\">]" "\\1" included "${include}")
        if(NOT EXISTS ${prefix}/include/${included})
            message(FATAL_ERROR "${header} includes ${included}, which is not installed")
        endif()
    endforeach()
    string(APPEND all_headers "#include <${header}>\n")
endforeach()
# The consumer also compiles one translation unit with every installed header.
file(WRITE ${WORK_DIR}/all_headers.cpp "${all_headers}")

set(flags -DCMAKE_BUILD_TYPE=Release -DCMAKE_PREFIX_PATH=${prefix} -DCMAKE_CXX_COMPILER=${CXX_COMPILER}
          -DKDRT_CONSUMER_EXTRA_SOURCES=${WORK_DIR}/all_headers.cpp)
if(SANITIZE)
    # The installed static libraries were compiled with the sanitizers: link their runtimes.
    list(APPEND flags "-DCMAKE_CXX_FLAGS=-fsanitize=address,undefined"
                      "-DCMAKE_EXE_LINKER_FLAGS=-fsanitize=address,undefined")
endif()
run(${CMAKE_COMMAND} -S ${CONSUMER_DIR} -B ${WORK_DIR}/build -G ${GENERATOR} ${flags})
run(${CMAKE_COMMAND} --build ${WORK_DIR}/build)
run(${WORK_DIR}/build/kdrt_consumer)
if(NOT run_output MATCHES "consumer ok")
    message(FATAL_ERROR "unexpected consumer output: ${run_output}")
endif()
message(STATUS "${run_output}")
run(${prefix}/bin/kdrt --version)
if(NOT run_output MATCHES "^kdrt [0-9]")
    message(FATAL_ERROR "the installed kdrt printed: ${run_output}")
endif()
file(REMOVE_RECURSE ${WORK_DIR})
