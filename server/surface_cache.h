#pragma once
/// The SurfaceIndex (kdrt/distance.h: pseudonormals, closed or not) of each tree that distance
/// queries have used, built once per resident tree on its first distance query and dropped when
/// the tree is gone (evicted and no request holds it). Not counted in memory_budget: 84 bytes
/// per triangle, about a quarter of the tree's own size. Thread-safe; concurrent first queries of
/// one tree may build its index twice (the first stored wins), never block other meshes.

#include <map>
#include <memory>
#include <mutex>

#include "kdrt/distance.h"
#include "kdrt/kdtree.h"

namespace kdrt::server {

class SurfaceCache {
public:
    /// The index of `tree`, building it (outside the lock) if this tree has none yet.
    [[nodiscard]] std::shared_ptr<const SurfaceIndex> get(
        const std::shared_ptr<const KdTree>& tree) {
        {
            std::lock_guard lock(mutex_);
            auto it = entries_.find(tree.get());
            if (it != entries_.end() && it->second.tree.lock() == tree) return it->second.index;
        }
        auto index = std::make_shared<const SurfaceIndex>(build_surface_index(*tree));
        std::lock_guard lock(mutex_);
        for (auto it = entries_.begin(); it != entries_.end();)
            it = it->second.tree.expired() ? entries_.erase(it) : std::next(it);
        auto [it, inserted] = entries_.try_emplace(tree.get(), Entry{tree, index});
        if (!inserted && it->second.tree.lock() != tree) it->second = Entry{tree, index};
        return it->second.index;
    }

private:
    struct Entry {
        std::weak_ptr<const KdTree> tree;
        std::shared_ptr<const SurfaceIndex> index;
    };
    std::mutex mutex_;
    std::map<const KdTree*, Entry> entries_;
};

}  // namespace kdrt::server
