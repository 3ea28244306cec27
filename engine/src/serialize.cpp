// Tree blob, all little-endian:
//
//   offset  size  field
//   0       8     magic "KDRTTREE"
//   8       4     u32 format version (kTreeFormatVersion)
//   12      4     u32 section size of the fixed header that follows (kFixedBytes)
//   16      28    build options: u32 builder, f32 traversal_cost, f32 intersection_cost,
//                 f32 empty_bonus, i32 max_depth, u32 middle_leaf_size, i32 middle_max_depth
//   44      92    stats: u64 triangles, nodes, leaves, empty_leaves, refs; u32 max_depth;
//                 f64 mean_leaf_depth, mean_tris_per_leaf, sah_cost; u64 bytes;
//                 f64 bytes_per_triangle, build_ms
//   136     24    bounds: f32 lo.xyz, hi.xyz
//   160     24    u64 node count, u64 ref count, u64 triangle count
//   184     ...   nodes (u32 word0, u32 word1 each), refs (u32 each), triangles (9 f32 each)
//   end-8   8     u64 checksum of every byte before it
#include "kdrt/serialize.h"

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstring>
#include <string>
#include <utility>

namespace kdrt {
namespace {

static_assert(std::endian::native == std::endian::little, "the tree blob is written in host order");

constexpr char kMagic[8] = {'K', 'D', 'R', 'T', 'T', 'R', 'E', 'E'};
constexpr uint32_t kFixedBytes = 28 + 92 + 24 + 24;
constexpr size_t kPrefixBytes = 16;

uint64_t checksum(const std::byte* data, size_t size) noexcept {
    // A fast 64-bit mix over 8-byte words: detects corruption, not an adversary.
    uint64_t h = 0x9E3779B97F4A7C15ull ^ size;
    size_t i = 0;
    for (; i + 8 <= size; i += 8) {
        uint64_t w;
        std::memcpy(&w, data + i, 8);
        h = std::rotl(h ^ (w * 0xC2B2AE3D27D4EB4Full), 31) * 0x9E3779B97F4A7C15ull;
    }
    uint64_t tail = 0;
    std::memcpy(&tail, data + i, size - i);
    h = std::rotl(h ^ (tail * 0xC2B2AE3D27D4EB4Full), 31) * 0x9E3779B97F4A7C15ull;
    h ^= h >> 33;
    h *= 0xFF51AFD7ED558CCDull;
    h ^= h >> 33;
    return h;
}

class Writer {
public:
    template <class T>
    void put(const T& value) {
        static_assert(std::is_trivially_copyable_v<T>);
        const size_t at = out_.size();
        out_.resize(at + sizeof(T));
        std::memcpy(out_.data() + at, &value, sizeof(T));
    }
    void put_bytes(const void* data, size_t size) {
        const size_t at = out_.size();
        out_.resize(at + size);
        if (size) std::memcpy(out_.data() + at, data, size);
    }
    std::vector<std::byte>& bytes() { return out_; }

private:
    std::vector<std::byte> out_;
};

class Reader {
public:
    explicit Reader(std::span<const std::byte> data) : data_(data) {}
    template <class T>
    T get(const char* what) {
        T value;
        need(sizeof(T), what);
        std::memcpy(&value, data_.data() + at_, sizeof(T));
        at_ += sizeof(T);
        return value;
    }
    void get_bytes(void* dst, size_t size, const char* what) {
        need(size, what);
        if (size) std::memcpy(dst, data_.data() + at_, size);
        at_ += size;
    }
    [[nodiscard]] size_t remaining() const { return data_.size() - at_; }
    [[nodiscard]] size_t offset() const { return at_; }

private:
    void need(size_t size, const char* what) const {
        if (remaining() < size) {
            throw TreeFormatError(std::string("tree blob truncated in ") + what + " at byte " +
                                  std::to_string(at_) + " (need " + std::to_string(size) +
                                  " bytes, have " + std::to_string(remaining()) + ")");
        }
    }
    std::span<const std::byte> data_;
    size_t at_ = 0;
};

void validate_structure(const KdTree& tree) {
    const size_t n = tree.nodes.size();
    if (n == 0) throw TreeFormatError("tree blob has no nodes");
    std::vector<uint8_t> depth(n, 0);
    std::vector<std::pair<uint32_t, size_t>> runs;  // (first reference, node) of non-empty leaves
    for (size_t i = 0; i < n; ++i) {
        const KdNode node = tree.nodes[i];
        if (node.is_leaf()) {
            const uint64_t end = uint64_t{node.first_ref()} + node.prim_count();
            if (end > tree.leaf_refs.size()) {
                throw TreeFormatError("node " + std::to_string(i) + ": leaf references " +
                                      std::to_string(end) + " exceed the " +
                                      std::to_string(tree.leaf_refs.size()) + " stored references");
            }
            if (node.prim_count() > 0) runs.emplace_back(node.first_ref(), i);
            continue;
        }
        const uint64_t child = node.first_child();
        // Children always follow their parent in the depth-first layout: no cycles possible.
        if (child <= i || child + 1 >= n) {
            throw TreeFormatError("node " + std::to_string(i) + ": child index " +
                                  std::to_string(child) + " out of range");
        }
        if (!std::isfinite(node.split()))
            throw TreeFormatError("node " + std::to_string(i) + ": split is not finite");
        const uint8_t d = static_cast<uint8_t>(depth[i] + 1);
        if (d > kMaxDepth)
            throw TreeFormatError("tree blob is deeper than " + std::to_string(kMaxDepth) +
                                  " levels");
        depth[child] = std::max(depth[child], d);
        depth[child + 1] = std::max(depth[child + 1], d);
    }
    // A kernel reads a leaf's run up to its last reference (KdTree::kLastRef): runs must not
    // overlap (every build writes them apart, one after another).
    std::sort(runs.begin(), runs.end());
    for (size_t k = 1; k < runs.size(); ++k) {
        const uint64_t end =
            uint64_t{runs[k - 1].first} + tree.nodes[runs[k - 1].second].prim_count();
        if (end > runs[k].first) {
            throw TreeFormatError("node " + std::to_string(runs[k].second) +
                                  ": leaf references overlap those of node " +
                                  std::to_string(runs[k - 1].second));
        }
    }
    for (size_t i = 0; i < tree.leaf_refs.size(); ++i) {
        if (tree.leaf_refs[i] >= tree.tris.size()) {
            throw TreeFormatError("reference " + std::to_string(i) + " names triangle " +
                                  std::to_string(tree.leaf_refs[i]) + " of " +
                                  std::to_string(tree.tris.size()));
        }
    }
}

}  // namespace

std::vector<std::byte> serialize_tree(const KdTree& tree) {
    Writer w;
    w.bytes().reserve(kPrefixBytes + kFixedBytes + tree.nodes.size() * 8 +
                      tree.leaf_refs.size() * 4 + tree.tris.size() * (sizeof(TriVerts) + 4) + 8);
    w.put_bytes(kMagic, sizeof kMagic);
    w.put(kTreeFormatVersion);
    w.put(kFixedBytes);
    const BuildOptions& o = tree.options;
    w.put(static_cast<uint32_t>(o.builder));
    w.put(o.traversal_cost);
    w.put(o.intersection_cost);
    w.put(o.empty_bonus);
    w.put(static_cast<int32_t>(o.max_depth));
    w.put(o.middle_leaf_size);
    w.put(static_cast<int32_t>(o.middle_max_depth));
    const TreeStats& s = tree.stats;
    w.put(s.triangles);
    w.put(s.nodes);
    w.put(s.leaves);
    w.put(s.empty_leaves);
    w.put(s.refs);
    w.put(s.max_depth);
    w.put(s.mean_leaf_depth);
    w.put(s.mean_tris_per_leaf);
    w.put(s.sah_cost);
    w.put(s.bytes);
    w.put(s.bytes_per_triangle);
    w.put(s.build_ms);
    for (int a = 0; a < 3; ++a) w.put(tree.bounds.lo[a]);
    for (int a = 0; a < 3; ++a) w.put(tree.bounds.hi[a]);
    w.put(static_cast<uint64_t>(tree.nodes.size()));
    w.put(static_cast<uint64_t>(tree.leaf_refs.size()));
    w.put(static_cast<uint64_t>(tree.tris.size()));
    for (const KdNode& node : tree.nodes) {
        w.put(node.word0());
        w.put(node.word1());
    }
    // The blob stores plain indices: the marks of the leaves' last references are derived.
    for (const uint32_t ref : tree.leaf_refs) w.put(ref & ~KdTree::kLastRef);
    w.put_bytes(tree.tris.data(), tree.tris.size() * sizeof(TriVerts));
    w.put_bytes(tree.tri_ids.data(), tree.tri_ids.size() * sizeof(uint32_t));
    w.put(checksum(w.bytes().data(), w.bytes().size()));
    return std::move(w.bytes());
}

KdTree deserialize_tree(std::span<const std::byte> blob) {
    Reader r(blob);
    char magic[8];
    r.get_bytes(magic, sizeof magic, "magic");
    if (std::memcmp(magic, kMagic, sizeof kMagic) != 0)
        throw TreeFormatError("not a kdrt tree blob (bad magic)");
    const auto version = r.get<uint32_t>("version");
    if (version != kTreeFormatVersion) {
        throw TreeFormatError("tree blob format version " + std::to_string(version) +
                              " is not supported (this build reads version " +
                              std::to_string(kTreeFormatVersion) + ")");
    }
    const auto fixed = r.get<uint32_t>("header size");
    if (fixed != kFixedBytes) {
        throw TreeFormatError("tree blob header size " + std::to_string(fixed) + ", expected " +
                              std::to_string(kFixedBytes));
    }
    if (blob.size() < kPrefixBytes + kFixedBytes + 8)
        throw TreeFormatError("tree blob truncated: " + std::to_string(blob.size()) + " bytes");
    uint64_t stored_sum;
    std::memcpy(&stored_sum, blob.data() + blob.size() - 8, 8);
    if (checksum(blob.data(), blob.size() - 8) != stored_sum)
        throw TreeFormatError("tree blob checksum mismatch (corrupted data)");

    KdTree tree;
    BuildOptions& o = tree.options;
    const auto builder = r.get<uint32_t>("options");
    if (builder > static_cast<uint32_t>(Builder::kMiddle))
        throw TreeFormatError("tree blob names unknown builder " + std::to_string(builder));
    o.builder = static_cast<Builder>(builder);
    o.traversal_cost = r.get<float>("options");
    o.intersection_cost = r.get<float>("options");
    o.empty_bonus = r.get<float>("options");
    o.max_depth = r.get<int32_t>("options");
    o.middle_leaf_size = r.get<uint32_t>("options");
    o.middle_max_depth = r.get<int32_t>("options");
    TreeStats& s = tree.stats;
    s.triangles = r.get<uint64_t>("stats");
    s.nodes = r.get<uint64_t>("stats");
    s.leaves = r.get<uint64_t>("stats");
    s.empty_leaves = r.get<uint64_t>("stats");
    s.refs = r.get<uint64_t>("stats");
    s.max_depth = r.get<uint32_t>("stats");
    s.mean_leaf_depth = r.get<double>("stats");
    s.mean_tris_per_leaf = r.get<double>("stats");
    s.sah_cost = r.get<double>("stats");
    s.bytes = r.get<uint64_t>("stats");
    s.bytes_per_triangle = r.get<double>("stats");
    s.build_ms = r.get<double>("stats");
    for (int a = 0; a < 3; ++a) tree.bounds.lo[a] = r.get<float>("bounds");
    for (int a = 0; a < 3; ++a) tree.bounds.hi[a] = r.get<float>("bounds");
    const auto node_count = r.get<uint64_t>("counts");
    const auto ref_count = r.get<uint64_t>("counts");
    const auto tri_count = r.get<uint64_t>("counts");
    const uint64_t payload = r.remaining() - 8;
    // Each count is bounded by the bytes present before anything is allocated.
    if (node_count > payload / 8 || ref_count > payload / 4 ||
        tri_count > payload / (sizeof(TriVerts) + 4) ||
        node_count * 8 + ref_count * 4 + tri_count * (sizeof(TriVerts) + 4) != payload) {
        throw TreeFormatError("tree blob sizes disagree: " + std::to_string(node_count) +
                              " nodes, " + std::to_string(ref_count) + " refs, " +
                              std::to_string(tri_count) + " triangles in " +
                              std::to_string(payload) + " bytes");
    }
    if (tri_count > kMaxTriangles || node_count > KdNode::kMaxField)
        throw TreeFormatError("tree blob counts exceed the format's limits");
    tree.nodes.resize(node_count);
    for (auto& node : tree.nodes) {
        const auto w0 = r.get<uint32_t>("nodes");
        const auto w1 = r.get<uint32_t>("nodes");
        node = KdNode::from_words(w0, w1);
    }
    tree.leaf_refs.resize(ref_count);
    r.get_bytes(tree.leaf_refs.data(), ref_count * sizeof(uint32_t), "refs");
    tree.tris.resize(tri_count);
    r.get_bytes(tree.tris.data(), tri_count * sizeof(TriVerts), "triangles");
    tree.tri_ids.resize(tri_count);
    r.get_bytes(tree.tri_ids.data(), tri_count * sizeof(uint32_t), "triangle ids");
    // tri_ids must be a permutation of the mesh ids; tri_slots is its inverse.
    tree.tri_slots.assign(tri_count, ~0u);
    for (size_t slot = 0; slot < tri_count; ++slot) {
        const uint32_t id = tree.tri_ids[slot];
        if (id >= tri_count || tree.tri_slots[id] != ~0u) {
            throw TreeFormatError("triangle " + std::to_string(slot) + " has id " +
                                  std::to_string(id) + ", out of range or repeated");
        }
        tree.tri_slots[id] = static_cast<uint32_t>(slot);
    }
    validate_structure(tree);
    mark_leaf_runs(tree.nodes, tree.leaf_refs);
    // The wide nodes are derived, not stored: a blob of this format from any build loads with
    // them, and the memory figures describe this process's arrays.
    tree.wide_nodes = make_wide_nodes(tree.nodes);
    const TreeStats now = compute_stats(tree);
    s.bytes = now.bytes;
    s.bytes_per_triangle = now.bytes_per_triangle;
    return tree;
}

}  // namespace kdrt
