// Replays fuzz inputs without libFuzzer: every regular file in each directory given on the command
// line (or the files themselves) goes through LLVMFuzzerTestOneInput once. A crash or trap fails
// the ctest test that runs it; a missing or empty corpus directory fails too, so a broken path
// cannot pass silently.

#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <vector>

#include "kdrt/proto/file_io.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size);

namespace {

bool replay(const std::filesystem::path& file) {
    const auto bytes = kdrt::proto::read_file_bytes(file);
    if (!bytes) {
        std::fprintf(stderr, "%s\n", bytes.error().c_str());
        return false;
    }
    // A private copy, so a read past the end is a heap overflow for the sanitizers.
    std::vector<uint8_t> copy(bytes->size());
    std::transform(bytes->begin(), bytes->end(), copy.begin(),
                   [](std::byte b) { return static_cast<uint8_t>(b); });
    LLVMFuzzerTestOneInput(copy.data(), copy.size());
    return true;
}

}  // namespace

int main(int argc, char** argv) {
    if (argc < 2) {
        std::fprintf(stderr, "usage: %s CORPUS_DIR_OR_FILE...\n", argv[0]);
        return 2;
    }
    size_t replayed = 0;
    for (int i = 1; i < argc; ++i) {
        const std::filesystem::path arg = argv[i];
        std::error_code ec;
        if (std::filesystem::is_directory(arg, ec)) {
            std::vector<std::filesystem::path> files;
            for (const auto& entry : std::filesystem::directory_iterator(arg, ec)) {
                if (entry.is_regular_file()) files.push_back(entry.path());
            }
            if (ec) {
                std::fprintf(stderr, "cannot list %s: %s\n", arg.c_str(), ec.message().c_str());
                return 1;
            }
            std::sort(files.begin(), files.end());
            if (files.empty()) {
                std::fprintf(stderr, "corpus directory %s is empty\n", arg.c_str());
                return 1;
            }
            for (const auto& file : files) {
                if (!replay(file)) return 1;
                ++replayed;
            }
        } else {
            if (!replay(arg)) return 1;
            ++replayed;
        }
    }
    std::printf("replayed %zu inputs\n", replayed);
    return 0;
}
