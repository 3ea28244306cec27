// STL mesh parser (binary/ascii detection included): never crashes; a parsed mesh is
// well-formed and round-trips through the binary or the ascii writer.

#include "fuzz_check.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    const bool binary = size % 2 == 0;
    kdrt::fuzz::fuzz_mesh(data, size, kdrt::proto::MeshFormat::kStl, {.binary = binary});
    return 0;
}
