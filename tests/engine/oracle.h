#pragma once
// The brute-force oracle applied to a whole ray set, and the comparison the tests assert.

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <span>
#include <vector>

#include <tbb/parallel_for.h>

#include "kdrt/trace.h"
#include "ray_prep.h"  // the engine's own triangle test, so the oracle decides hits identically

namespace kdrt::test {

/// Brute force made affordable for big meshes: every triangle whose box, grown by a margin far
/// above any rounding of the triangle test (2^-12 of the scene size), the ray passes through is
/// handed to the same exact test as kdrt::brute_force_intersect, in triangle order with the same
/// tie rule. The box test is only a conservative filter, so the answers are the plain brute
/// force's; OracleSelfCheck.FilteredBruteForceEqualsPlain verifies that.
class FilteredBruteForce {
public:
    explicit FilteredBruteForce(std::span<const TriVerts> tris) : tris_(tris) {
        float scale = 0;
        for (const TriVerts& t : tris)
            for (int a = 0; a < 3; ++a)
                scale =
                    std::max({scale, std::fabs(t.v0[a]), std::fabs(t.v1[a]), std::fabs(t.v2[a])});
        const float margin = scale * 0x1p-12f;
        for (int a = 0; a < 3; ++a) {
            lo_[a].resize(tris.size());
            hi_[a].resize(tris.size());
        }
        for (size_t i = 0; i < tris.size(); ++i) {
            for (int a = 0; a < 3; ++a) {
                lo_[a][i] = std::min({tris[i].v0[a], tris[i].v1[a], tris[i].v2[a]}) - margin;
                hi_[a][i] = std::max({tris[i].v0[a], tris[i].v1[a], tris[i].v2[a]}) + margin;
            }
        }
    }

    [[nodiscard]] Hit intersect(const Ray& ray) const {
        if (!detail::ray_is_valid(ray)) return Hit{};
        const detail::PreparedRay prepared = detail::prepare_ray(ray);
        Hit best;
        best.t = ray.tmax;
        const float o[3] = {ray.ox, ray.oy, ray.oz}, d[3] = {ray.dx, ray.dy, ray.dz};
        float inv[3];
        // A zero component gets a huge finite reciprocal instead of infinity: no NaN, and a ray on
        // a grown box's face cannot touch the triangle inside it anyway.
        for (int a = 0; a < 3; ++a) inv[a] = d[a] == 0.0f ? 1e30f : 1.0f / d[a];
        constexpr size_t kBlock = 256;
        alignas(64) uint8_t pass[kBlock];
        for (size_t base = 0; base < tris_.size(); base += kBlock) {
            const size_t n = std::min(kBlock, tris_.size() - base);
            const float tmax = best.t;
            const float *lx = lo_[0].data() + base, *ly = lo_[1].data() + base,
                        *lz = lo_[2].data() + base;
            const float *hx = hi_[0].data() + base, *hy = hi_[1].data() + base,
                        *hz = hi_[2].data() + base;
            for (size_t j = 0; j < n; ++j) {  // branch-free, so the compiler vectorises it
                const float x0 = (lx[j] - o[0]) * inv[0], x1 = (hx[j] - o[0]) * inv[0];
                const float y0 = (ly[j] - o[1]) * inv[1], y1 = (hy[j] - o[1]) * inv[1];
                const float z0 = (lz[j] - o[2]) * inv[2], z1 = (hz[j] - o[2]) * inv[2];
                const float xn = x0 < x1 ? x0 : x1, xf = x0 < x1 ? x1 : x0;
                const float yn = y0 < y1 ? y0 : y1, yf = y0 < y1 ? y1 : y0;
                const float zn = z0 < z1 ? z0 : z1, zf = z0 < z1 ? z1 : z0;
                float tnear = xn > yn ? xn : yn;
                tnear = tnear > zn ? tnear : zn;
                tnear = tnear > ray.tmin ? tnear : ray.tmin;
                float tfar = xf < yf ? xf : yf;
                tfar = tfar < zf ? tfar : zf;
                tfar = tfar < tmax ? tfar : tmax;
                // A hit at t lies inside the grown box for [t - margin/|d|, t + margin/|d|], an
                // interval far longer than the rounding here, so a plain comparison is safe.
                pass[j] = tnear <= tfar;
            }
            for (size_t j = 0; j < n; ++j) {
                if (!pass[j]) continue;
                const auto prim = static_cast<uint32_t>(base + j);
                float t, u, v;
                if (!detail::intersect_triangle(prepared, tris_[prim], ray.tmin, t, u, v)) continue;
                if (t < best.t || (t == best.t && prim < best.prim)) best = {t, prim, u, v};
            }
        }
        return best.is_hit() ? best : Hit{};
    }

private:
    std::span<const TriVerts> tris_;
    std::vector<float> lo_[3], hi_[3];
};

inline std::vector<Hit> brute_force_all(std::span<const TriVerts> tris, std::span<const Ray> rays) {
    std::vector<Hit> hits(rays.size());
    if (tris.size() < 1024) {
        tbb::parallel_for(size_t{0}, rays.size(),
                          [&](size_t i) { hits[i] = brute_force_intersect(tris, rays[i]); });
    } else {
        const FilteredBruteForce oracle(tris);
        tbb::parallel_for(size_t{0}, rays.size(),
                          [&](size_t i) { hits[i] = oracle.intersect(rays[i]); });
    }
    return hits;
}

inline std::vector<Hit> tree_all(const KdTree& tree, std::span<const Ray> rays) {
    std::vector<Hit> hits(rays.size());
    intersect_single(tree, rays, hits);
    return hits;
}

/// Asserts the tree's answers equal the oracle's: same t, triangle, u and v. Both break ties at
/// equal t by the lowest triangle id, but a tree may legitimately not visit a tied triangle in a
/// cell it has no reason to enter; such a tie is accepted when t agrees exactly and the tree's
/// triangle really is hit there (its own brute-force test gives the same t, u, v). Ties are
/// counted and reported.
inline void expect_same_hits(std::span<const Hit> got, std::span<const Hit> want,
                             std::span<const Ray> rays, std::span<const TriVerts> tris = {}) {
    ASSERT_EQ(got.size(), want.size());
    size_t mismatches = 0, ties = 0;
    for (size_t i = 0; i < got.size(); ++i) {
        if (std::memcmp(&got[i], &want[i], sizeof(Hit)) == 0) continue;
        if (!tris.empty() && got[i].is_hit() && got[i].t == want[i].t &&
            got[i].prim < tris.size()) {
            const Hit alone = brute_force_intersect(tris.subspan(got[i].prim, 1), rays[i]);
            if (alone.t == got[i].t && alone.u == got[i].u && alone.v == got[i].v) {
                ++ties;
                continue;
            }
        }
        if (++mismatches <= 5) {
            const Ray& r = rays[i];
            ADD_FAILURE() << "ray " << i << " o=(" << r.ox << "," << r.oy << "," << r.oz << ") d=("
                          << r.dx << "," << r.dy << "," << r.dz << ") [" << r.tmin << "," << r.tmax
                          << "]: got t=" << got[i].t << " prim=" << got[i].prim << " u=" << got[i].u
                          << " v=" << got[i].v << ", want t=" << want[i].t
                          << " prim=" << want[i].prim << " u=" << want[i].u << " v=" << want[i].v;
        }
    }
    EXPECT_EQ(mismatches, 0u) << "of " << got.size() << " rays";
    if (ties)
        std::printf("    %zu of %zu rays had an exact tie broken differently\n", ties, got.size());
}

}  // namespace kdrt::test
