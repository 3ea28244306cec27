#include "store/tree_file.h"

#include <cstring>

#include "kdrt/serialize.h"

namespace kdrt::server {
namespace {

constexpr char kMagic[8] = {'K', 'D', 'R', 'T', 'S', 'T', 'R', 'E'};
constexpr char kEngineMagic[8] = {'K', 'D', 'R', 'T', 'T', 'R', 'E', 'E'};
constexpr size_t kIdOffset = 16, kIdBytes = 64, kBlobBytesOffset = 80, kChecksumOffset = 88;

uint64_t fnv1a(std::span<const std::byte> bytes) {
    uint64_t h = 0xcbf29ce484222325ull;
    for (const std::byte b : bytes) {
        h ^= static_cast<uint8_t>(b);
        h *= 0x100000001b3ull;
    }
    return h;
}

template <typename T>
T read_le(std::span<const std::byte> bytes, size_t offset) {
    T value = 0;
    for (size_t i = 0; i < sizeof(T); ++i)
        value |= static_cast<T>(static_cast<uint8_t>(bytes[offset + i])) << (8 * i);
    return value;
}

template <typename T>
void write_le(std::vector<std::byte>& out, size_t offset, T value) {
    for (size_t i = 0; i < sizeof(T); ++i)
        out[offset + i] = static_cast<std::byte>((value >> (8 * i)) & 0xff);
}

bool starts_with(std::span<const std::byte> bytes, const char (&magic)[8]) {
    return bytes.size() >= 8 && std::memcmp(bytes.data(), magic, 8) == 0;
}

proto::Err<TreeFileProblem> problem(TreeFileProblem::Reason reason, std::string detail) {
    return proto::Err{TreeFileProblem{reason, std::move(detail)}};
}

}  // namespace

std::string_view reason_label(TreeFileProblem::Reason reason) noexcept {
    switch (reason) {
        case TreeFileProblem::Reason::kMissing:
            return "missing";
        case TreeFileProblem::Reason::kUnreadable:
            return "unreadable";
        case TreeFileProblem::Reason::kTruncated:
            return "truncated";
        case TreeFileProblem::Reason::kCorrupt:
            return "corrupt";
        case TreeFileProblem::Reason::kFormatVersion:
            return "format_version";
        case TreeFileProblem::Reason::kOtherMesh:
            return "other_mesh";
    }
    return "corrupt";
}

std::vector<std::byte> encode_tree_file(std::string_view id, const KdTree& tree) {
    const std::vector<std::byte> blob = serialize_tree(tree);
    std::vector<std::byte> out(kTreeFileHeaderBytes + blob.size());
    std::memcpy(out.data(), kMagic, sizeof kMagic);
    write_le<uint32_t>(out, 8, kTreeFileVersion);
    write_le<uint32_t>(out, 12, static_cast<uint32_t>(kTreeFileHeaderBytes));
    for (size_t i = 0; i < kIdBytes; ++i)
        out[kIdOffset + i] = static_cast<std::byte>(i < id.size() ? id[i] : ' ');
    write_le<uint64_t>(out, kBlobBytesOffset, blob.size());
    write_le<uint64_t>(out, kChecksumOffset,
                       fnv1a(std::span<const std::byte>(out).first(kChecksumOffset)));
    std::memcpy(out.data() + kTreeFileHeaderBytes, blob.data(), blob.size());
    return out;
}

proto::Result<KdTree, TreeFileProblem> decode_tree_file(std::string_view id,
                                                        std::span<const std::byte> file) {
    using Reason = TreeFileProblem::Reason;
    if (starts_with(file, kEngineMagic))
        return problem(Reason::kFormatVersion,
                       "a bare engine tree blob from before the store's tree file format (it does "
                       "not name its mesh)");
    if (file.size() < kTreeFileHeaderBytes) {
        if (file.size() >= 8 && !starts_with(file, kMagic))
            return problem(Reason::kCorrupt, "not a kdrt tree file (bad magic)");
        return problem(Reason::kTruncated,
                       "truncated: " + std::to_string(file.size()) + " bytes, shorter than the " +
                           std::to_string(kTreeFileHeaderBytes) + "-byte header");
    }
    if (!starts_with(file, kMagic))
        return problem(Reason::kCorrupt, "not a kdrt tree file (bad magic)");
    if (read_le<uint64_t>(file, kChecksumOffset) != fnv1a(file.first(kChecksumOffset)))
        return problem(Reason::kCorrupt, "header checksum mismatch");
    const uint32_t version = read_le<uint32_t>(file, 8);
    if (version != kTreeFileVersion || read_le<uint32_t>(file, 12) != kTreeFileHeaderBytes)
        return problem(Reason::kFormatVersion,
                       "tree file format version " + std::to_string(version) +
                           ", this server reads " + std::to_string(kTreeFileVersion));
    const std::string_view owner(reinterpret_cast<const char*>(file.data() + kIdOffset), kIdBytes);
    if (owner != id)
        return problem(Reason::kOtherMesh,
                       "the tree of mesh " + std::string(owner) + ", not of this mesh");
    const uint64_t blob_bytes = read_le<uint64_t>(file, kBlobBytesOffset);
    const uint64_t actual = file.size() - kTreeFileHeaderBytes;
    if (blob_bytes != actual)
        return problem(Reason::kTruncated, "the header says " + std::to_string(blob_bytes) +
                                               " blob bytes, the file holds " +
                                               std::to_string(actual));
    const std::span<const std::byte> blob = file.subspan(kTreeFileHeaderBytes);
    if (starts_with(blob, kEngineMagic) && blob.size() >= 12) {
        const uint32_t engine_version = read_le<uint32_t>(blob, 8);
        if (engine_version != kTreeFormatVersion)
            return problem(Reason::kFormatVersion,
                           "engine tree format version " + std::to_string(engine_version) +
                               ", this build reads " + std::to_string(kTreeFormatVersion));
    }
    try {
        return deserialize_tree(blob);
    } catch (const TreeFormatError& e) {
        return problem(Reason::kCorrupt, e.what());
    }
}

}  // namespace kdrt::server
