#pragma once
// Internal: a scene's single rays walked in turn (scene_in_turn_ops, scene_in_turn_ops.h): the
// mesh batch's trace_in_turn (packet_kernel.h) one level up. Each of K rays in flight is a small
// state machine: its top-level walk (TopWalk, to its next leaf and through that leaf's instances),
// then the object-space walk of an instance it reaches (the mesh's single-ray walk, wide_start and
// wide_step of wide_kernel.h, one cell a turn), then back to the top level. The walks advance in
// turn, one cell each, and the line of the cell a walk moves to is prefetched, so the dependent
// loads of different rays overlap. A ray meets the instances intersect_one / occluded_one
// (scene_trace.cpp) meets, in the same order, each traced with the same object ray and tmax, and
// each instance's walk is the single-ray kernel's, so every answer is theirs bit for bit.
//
// Include this only from a per-ISA translation unit, after its `#pragma GCC target` (and after
// scene_internal.h, outside it): everything here is in an anonymous namespace, each ISA's copy
// compiled for its own target (simd.h, wide_kernel.h).

#include <cstddef>

#include "scene_in_turn_ops.h"
#include "scene_internal.h"
#include "wide_kernel.h"

namespace kdrt::detail {
namespace {
namespace in_turn {

/// clip_widened(p, box, tmin, tmax)'s answer (whether the widened segment reaches `box`) for a
/// ray with no zero direction component: clip_box's segment is not empty.
[[gnu::always_inline]] inline bool reaches_box(const TopRay& p, const Aabb& box, float tmin,
                                               float tmax) noexcept {
    const TopSegment c = clip_box(p, box, tmin, tmax);
    return c.entry <= c.exit;
}

/// One ray in flight: its top-level walk, where it stands in a leaf's references, its answer so
/// far, and the object-space walk of the instance it is tracing (when `in_instance`).
struct Flight {
    size_t index;  ///< the ray's index in the batch
    TopRay p;
    TopWalk walk;
    Mailbox mailbox;
    SceneHit best;  ///< closest hit so far ((ray.tmax, kNoHit) while none)
    uint32_t ref, ref_end;
    uint32_t geom;  ///< the instance being traced
    bool in_instance;
    bool flat;       ///< a zero direction component (clip_widened's own case)
    bool leaf_next;  ///< the instance walk's cell is a leaf whose triangles are not prefetched yet
    /// The mesh tree `arrays` were loaded from (nullptr: none yet): instances of one mesh share
    /// its tree, and a visit to the same tree as the flight's last loads nothing again.
    const KdTree* tree;
    union Arrays {
        WideArrays a;
        char none;
        Arrays() noexcept : none(0) {}
    } arrays;
    WideWalk w;
};

/// Takes ray f.index's top-level walk on: through the rest of its current leaf's references, then
/// to the next leaves (TopWalk::next_leaf with the closest hit so far as the limit), to the next
/// instance it reaches and its mailbox has not seen, whose object-space walk it starts. True when
/// the top-level walk has ended (the ray is answered).
template <bool AnyHit>
[[gnu::always_inline]] inline bool advance_top(const SceneData& s, const Ray& ray, Flight& f,
                                               uint64_t& visits) noexcept {
    for (;;) {
        while (f.ref < f.ref_end) {
            const uint32_t geom = s.refs[f.ref++];
            float t0 = ray.tmin, t1 = AnyHit ? ray.tmax : f.best.t;
            if (f.flat ? !clip_widened(f.p, s.inst[geom].world, t0, t1)
                       : !reaches_box(f.p, s.inst[geom].world, t0, t1))
                continue;
            // No instance listed in two leaves (refs_unique): none can be met twice.
            if (!s.refs_unique && f.mailbox.seen(geom)) continue;
            ++visits;
            Ray o = to_object(s.inst[geom], ray);
            if constexpr (!AnyHit) o.tmax = f.best.t;
            const KdTree& tree = *s.instances[geom].tree;
            if (&tree != f.tree) {
                f.arrays.a = WideArrays(tree);
                f.tree = &tree;
            }
            // As intersect / occluded (kdrt/trace.h) start: a ray that is not valid in object
            // space or misses the tree's box has no hit there. (wide_start's check of the ray is
            // made here; its other, an empty tree, is the scene's: an instance of one has an
            // empty world box and is in no top-level leaf.)
            if (!ray_shape(o).valid || !wide_start<true>(tree, f.arrays.a, o, f.w.ray, f.w.cell))
                continue;
            f.w.best = {o.tmax, kNoHit, 0.0f, 0.0f};
            f.w.found = false;
            f.w.stack_size = 0;
            f.geom = geom;
            f.in_instance = true;
            f.leaf_next = false;
            prefetch_cell(f.arrays.a, f.w.cell.slot);
            return false;
        }
        const TopNode* leaf = f.walk.next_leaf(s, f.p, AnyHit ? ray.tmax : f.best.t);
        if (!leaf) return true;
        f.ref = leaf->first_ref();
        f.ref_end = f.ref + leaf->count();
    }
}

/// The batch: rays[0, count) walked K at a time; answers into hits (closest hit) or occluded
/// (AnyHit), instance visits added to `visits`.
template <bool AnyHit, int K>
[[gnu::always_inline]] inline void trace(const SceneData& s, const Ray* rays, size_t count,
                                         SceneHit* hits, uint8_t* occluded,
                                         uint64_t& visits) noexcept {
    Flight flight[K];      // NOLINT(cppcoreguidelines-pro-type-member-init): set by start
    wide::Stack stack[K];  // NOLINT(cppcoreguidelines-pro-type-member-init): written first
    TopCell top_cells[K][kTopStack];
    for (Flight& f : flight) f.tree = nullptr;
    size_t next = 0;
    const auto answer = [&](const Flight& f, bool hit) {
        if constexpr (AnyHit)
            occluded[f.index] = hit ? 1 : 0;
        else
            hits[f.index] = f.best.is_hit() ? f.best : SceneHit{};
    };
    // Starts flight k on the next ray that needs one and takes it to its first instance; false
    // when the batch is done.
    const auto start = [&](int k) {
        Flight& f = flight[k];
        while (next < count) {
            f.index = next++;
            const Ray& ray = rays[f.index];
            f.best = SceneHit{ray.tmax, kNoHit, 0.0f, 0.0f, kNoHit};
            const RayShape shape = ray_shape(ray);
            if (!shape.valid) {
                answer(f, false);  // no hit: prim is kNoHit
                continue;
            }
            f.p = make_top_ray(s, ray);
            f.flat = shape.flat;
            if (shape.flat) {
                f.walk.start(s, ray, f.p, top_cells[k]);
            } else {
                // TopWalk::start with clip_widened's root clip made by clip_box.
                f.walk.stack = top_cells[k];
                f.walk.size = 0;
                const TopSegment c = clip_box(f.p, s.bounds, ray.tmin, ray.tmax);
                if (!s.refs.empty() && c.entry <= c.exit)
                    f.walk.stack[f.walk.size++] = {0, c.entry, c.exit};
            }
            if (!s.refs_unique) f.mailbox = Mailbox{};
            f.ref = f.ref_end = 0;
            f.in_instance = false;
            if (advance_top<AnyHit>(s, ray, f, visits)) {
                answer(f, false);
                continue;
            }
            return true;
        }
        return false;
    };
    // Flight k's turn: one cell of its instance's walk, or the prefetch of a leaf's triangles;
    // where the instance's walk ends, the ray's top-level walk goes on to its next instance, or
    // the flight takes the next ray. False when flight k has ended with no ray left to take.
    const auto turn = [&](int k) __attribute__((always_inline)) {
        Flight& f = flight[k];
        if (f.leaf_next) {
            prefetch_leaf_triangles(f.arrays.a, f.w.cell.slot);
            f.leaf_next = false;
            return true;
        }
        if (!wide_step<AnyHit>(f.arrays.a, f.w.ray, stack[k], f.w.stack_size, f.w.cell, f.w.best,
                               f.w.found, NoCount{})) {
            prefetch_cell(f.arrays.a, f.w.cell.slot);
            f.leaf_next = WideNode::slot_tag(f.w.cell.slot) == WideNode::kSlotLeaf;
            return true;
        }
        // The instance's walk has ended: its answer is intersect's / occluded's.
        f.in_instance = false;
        bool ended;
        if constexpr (AnyHit) {
            ended = f.w.found || advance_top<AnyHit>(s, rays[f.index], f, visits);
            if (ended) answer(f, f.w.found);
        } else {
            if (f.w.found) {
                const SceneHit c{f.w.best.t, f.w.best.prim, f.w.best.u, f.w.best.v, f.geom};
                if (scene_hit_less(c, f.best)) f.best = c;
            }
            ended = advance_top<AnyHit>(s, rays[f.index], f, visits);
            if (ended) answer(f, false);
        }
        return !ended || start(k);
    };
    bool live[K];
    int n_live = 0;
    for (int k = 0; k < K; ++k) n_live += (live[k] = start(k)) ? 1 : 0;
    // While the batch has rays to start, every flight is live and its turns are taken without
    // a check; the first sweep in which a flight finds no ray ends this.
    for (bool all = n_live == K; all;) {
        for (int k = 0; k < K; ++k) {
            if (!turn(k)) {
                live[k] = false;
                --n_live;
                all = false;
            }
        }
    }
    while (n_live > 0) {
        for (int k = 0; k < K; ++k) {
            if (live[k] && !turn(k)) {
                live[k] = false;
                --n_live;
            }
        }
    }
}

void intersect_in_turn(const SceneData& s, const Ray* rays, size_t count, SceneHit* hits,
                       uint64_t& visits) noexcept {
    trace<false, kSceneWalksInTurn>(s, rays, count, hits, nullptr, visits);
}

void occluded_in_turn(const SceneData& s, const Ray* rays, size_t count, uint8_t* occluded,
                      uint64_t& visits) noexcept {
    trace<true, kSceneWalksInTurn>(s, rays, count, nullptr, occluded, visits);
}

}  // namespace in_turn
}  // namespace
}  // namespace kdrt::detail
