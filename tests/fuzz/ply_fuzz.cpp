// PLY mesh parser: never crashes; a parsed mesh is well-formed and round-trips. The first input
// byte picks the encoding of the rewrite, so all three writers are exercised.

#include "fuzz_check.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    const uint8_t pick = size > 0 ? data[0] : 0;
    kdrt::fuzz::fuzz_mesh(data, size, kdrt::proto::MeshFormat::kPly,
                          {.binary = (pick & 1) != 0, .big_endian = (pick & 2) != 0});
    return 0;
}
