# ctest client_install: installs the kdrt_client component (library, headers, CMake package, the
# kdrt binary) into a temp prefix, then configures, builds and runs tests/client/consumer, which
# uses find_package(kdrt) and links kdrt::client.
#   cmake -DBUILD_DIR=... -DCONSUMER_DIR=... -DWORK_DIR=... -DGENERATOR=... -DCXX_COMPILER=...
#         -DSANITIZE=ON|OFF -P install_test.cmake

function(run)
    execute_process(COMMAND ${ARGN} RESULT_VARIABLE rc OUTPUT_VARIABLE out ERROR_VARIABLE err)
    if(NOT rc EQUAL 0)
        string(REPLACE ";" " " command "${ARGN}")
        message(FATAL_ERROR "failed (${rc}): ${command}\n${out}\n${err}")
    endif()
    set(run_output "${out}" PARENT_SCOPE)
endfunction()

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

set(flags -DCMAKE_BUILD_TYPE=Release -DCMAKE_PREFIX_PATH=${prefix} -DCMAKE_CXX_COMPILER=${CXX_COMPILER})
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
