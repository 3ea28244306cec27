// OFF mesh parser: never crashes; a parsed mesh is well-formed and round-trips.

#include "fuzz_check.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    kdrt::fuzz::fuzz_mesh(data, size, kdrt::proto::MeshFormat::kOff);
    return 0;
}
