#include "store/store_check.h"

#include <string>
#include <vector>

#include "kdrt/proto/mesh_id.h"
#include "store/mesh_cache.h"
#include "store/mesh_store.h"

namespace kdrt::server {

int check_store(const ServerConfig& config, std::FILE* out) {
    const MeshStore store(config.cache_dir);
    auto listed = store.list();
    if (!listed) {
        std::fprintf(out, "kdrt-server: %s\n", listed.error().c_str());
        return 2;
    }
    size_t damaged = 0, lost = 0;
    for (const MeshStore::Listed& item : *listed) {
        std::vector<std::string> problems;
        auto mesh = store.load_mesh(item.id);
        if (!mesh) problems.push_back("mesh file: " + mesh.error().detail);
        auto tree = store.load_tree(item.id);
        if (!tree)
            problems.push_back("tree file (" + std::string(reason_label(tree.error().reason)) +
                               "): " + tree.error().detail);
        if (!item.summary) {
            problems.push_back("summary: " + item.summary_error);
        } else {
            if (tree) {
                if (auto why = summary_disagreement(*tree, *item.summary); !why.empty())
                    problems.push_back("summary: " + why);
            } else if (mesh) {
                const proto::MeshSummary fresh = make_summary(item.id, *mesh, KdTree{});
                if (fresh.triangles != item.summary->triangles)
                    problems.push_back("summary: says " + std::to_string(item.summary->triangles) +
                                       " triangles, the mesh file holds " +
                                       std::to_string(fresh.triangles));
            }
        }
        if (problems.empty()) {
            std::fprintf(out, "ok %s\n", item.id.c_str());
            continue;
        }
        ++damaged;
        // A verified mesh file, or a tree of this mesh, is enough to rebuild everything else.
        const bool repairable = mesh || (tree && proto::mesh_id(mesh_from_tree(*tree)) == item.id);
        if (!repairable) ++lost;
        std::string line =
            "damaged " + item.id + " (" +
            (repairable ? "repairable from what remains" : "not repairable: upload it again") +
            "):";
        for (const std::string& p : problems) line += "\n  " + p;
        std::fprintf(out, "%s\n", line.c_str());
    }
    std::fprintf(out, "checked %zu meshes in %s: %zu damaged (%zu not repairable)\n",
                 listed->size(), config.cache_dir.c_str(), damaged, lost);
    return damaged == 0 ? 0 : 1;
}

}  // namespace kdrt::server
