# daemon_install: `cmake --install` of every component into a staging prefix, then checks the
# layout (packaging/CMakeLists.txt), that the installed kdrt finds its image module, that the
# Python package imports from the install, and that the installed kdrt-server starts with the
# installed config, notifies systemd's socket and answers the installed kdrt's `health`.
#   cmake -DBUILD_DIR=... -DWORK_DIR=... -DPYTHON=... -P daemon_install_test.cmake

include(${CMAKE_CURRENT_LIST_DIR}/../common/run_command.cmake)

set(prefix ${WORK_DIR}/prefix)
file(REMOVE_RECURSE ${WORK_DIR})
run(${CMAKE_COMMAND} --install ${BUILD_DIR} --prefix ${prefix})

# The layout. The lib directory is GNUInstallDirs' (lib, or lib/<multiarch> under /usr).
file(GLOB module ${prefix}/lib*/kdrt/kdrt-image-module.so ${prefix}/lib/*/kdrt/kdrt-image-module.so)
foreach(file bin/kdrt bin/kdrt-server etc/kdrt/kdrt.json lib/systemd/system/kdrt.service
             lib/python3/dist-packages/kdrt/__init__.py share/doc/kdrt/README.md)
    if(NOT EXISTS ${prefix}/${file})
        message(FATAL_ERROR "the install has no ${file}")
    endif()
endforeach()
if(NOT module)
    message(FATAL_ERROR "the install has no <libdir>/kdrt/kdrt-image-module.so")
endif()
file(GLOB_RECURSE pycache ${prefix}/*/__pycache__/*)
if(pycache)
    message(FATAL_ERROR "__pycache__ was installed: ${pycache}")
endif()
file(READ ${prefix}/lib/systemd/system/kdrt.service unit)
if(NOT unit MATCHES "ExecStart=[^\n]*/bin/kdrt-server --config [^\n]*/kdrt/kdrt.json")
    message(FATAL_ERROR "the installed unit does not run the installed server with its config:\n${unit}")
endif()

# The installed kdrt loads its module from <bindir>/../<libdir>/kdrt: a split render gets past the
# module and fails on the closed port (exit 3), not on the module (exit 1).
execute_process(COMMAND ${prefix}/bin/kdrt render ${prefix} -o ${WORK_DIR}/x.png --split 2
                        --server http://127.0.0.1:9 --retries 0
                RESULT_VARIABLE rc ERROR_VARIABLE err OUTPUT_QUIET)
if(NOT rc EQUAL 3 OR err MATCHES "image module")
    message(FATAL_ERROR "the installed kdrt did not find its image module (exit ${rc}):\n${err}")
endif()

# The Python package from the install, not the source tree.
run(env -i PATH=/usr/bin:/bin PYTHONDONTWRITEBYTECODE=1
        PYTHONPATH=${prefix}/lib/python3/dist-packages ${PYTHON} -c
        "import kdrt, sys; assert kdrt.__file__.startswith(sys.argv[1]), kdrt.__file__; print(kdrt.__version__)"
        ${prefix})

# The installed server with the installed config, started as systemd's Type=notify would: it
# sends READY=1 to $NOTIFY_SOCKET, answers the installed kdrt's `health`, sends STOPPING=1 on
# SIGTERM and exits 0 (tests/packaging/notify_run.py).
get_filename_component(here ${CMAKE_CURRENT_LIST_FILE} DIRECTORY)
run(${PYTHON} ${here}/notify_run.py ${prefix}/bin/kdrt-server ${prefix}/etc/kdrt/kdrt.json
    ${prefix}/bin/kdrt ${WORK_DIR})
message(STATUS "${run_output}")
file(REMOVE_RECURSE ${WORK_DIR})
