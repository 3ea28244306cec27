# run(COMMAND...): runs a command in a CMake -P test script; a non-zero exit is a FATAL_ERROR with
# the command line, its output and its errors. Sets run_output and run_error in the caller.
function(run)
    execute_process(COMMAND ${ARGN} RESULT_VARIABLE rc OUTPUT_VARIABLE out ERROR_VARIABLE err)
    if(NOT rc EQUAL 0)
        string(REPLACE ";" " " command "${ARGN}")
        message(FATAL_ERROR "failed (${rc}): ${command}\n${out}\n${err}")
    endif()
    set(run_output "${out}" PARENT_SCOPE)
    set(run_error "${err}" PARENT_SCOPE)
endfunction()
