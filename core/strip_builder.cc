// Delaunay construction on all cores: strips, stitches, Lawson flips.
#include "core/strip_builder.h"

#include <CGAL/Constrained_Delaunay_triangulation_2.h>
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Triangulation_vertex_base_with_info_2.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <atomic>
#include <utility>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "core/cgal_builder.h"
#include "core/flip_rules.h"
#include "core/parallel.h"

namespace kinetri::core {
namespace {

using Kernel = CGAL::Exact_predicates_inexact_constructions_kernel;
using Vb = CGAL::Triangulation_vertex_base_with_info_2<uint32_t, Kernel>;
using Fb = CGAL::Constrained_triangulation_face_base_2<Kernel>;
using Tds = CGAL::Triangulation_data_structure_2<Vb, Fb>;
using Cdt =
    CGAL::Constrained_Delaunay_triangulation_2<Kernel, Tds,
                                               CGAL::Exact_predicates_tag>;

constexpr size_t kMinSitesPerStrip = size_t{1} << 15;
// More strips than threads: a strip's triangulation then stays closer to
// the cache (1M points, 2 threads: 2 strips 0.45 s a rebuild, 8 strips
// 0.40 s; stitching 7 seams costs about 4 ms).
constexpr size_t kStripsPerThread = 4;
constexpr uint32_t kMaxStrips = 64;
constexpr size_t kPivotSample = 4096;
// Strips whose hulls hold more than max(kMaxHullVertices, sites /
// kSitesPerHullVertex) vertices in all are not stitched (see below).
constexpr size_t kMaxHullVertices = 4096;
constexpr size_t kSitesPerHullVertex = 64;

uint64_t EdgeKey(uint32_t u, uint32_t v) { return (uint64_t{u} << 32) | v; }

// Every strip in one set of half-edge arrays; slots freed by a stitch are
// taken again before the arrays grow.
struct Assembly {
  std::vector<uint32_t> origin, twin;
  std::vector<uint32_t> free;

  uint32_t Allocate() {
    if (!free.empty()) {
      const uint32_t t = free.back();
      free.pop_back();
      return t;
    }
    const uint32_t t = static_cast<uint32_t>(origin.size() / 3);
    origin.resize(origin.size() + 3, kNoVertex);
    twin.resize(twin.size() + 3, kNoEdge);
    return t;
  }
  void Free(uint32_t t) {
    for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
      origin[e] = kNoVertex;
      twin[e] = kNoEdge;
    }
    free.push_back(t);
  }
  MeshView view() {
    return MeshView{origin.data(), twin.data(),
                    static_cast<uint32_t>(origin.size())};
  }
};

// The half-edge of ghost triangle t that runs along its hull edge.
uint32_t GhostBase(const std::vector<uint32_t>& origin, uint32_t t) {
  for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
    if (origin[e] != kInfiniteVertex && origin[Next(e)] != kInfiniteVertex) {
      return e;
    }
  }
  return kNoEdge;
}

// Stitches strip `b` (its ghost triangles `ghosts_b`) to the union of the
// strips before it (ghosts *ghosts_a), then makes the result Delaunay. The
// ghosts of both go; the gap between the two convex hulls and the new hull
// come from a constrained triangulation of the hull vertices of both with
// every hull edge a constraint: its faces with vertices on both sides fill
// the gap (a face with all three on one side lies in that side's convex
// hull, which is already triangulated), its infinite faces are the new
// ghosts. On return *ghosts_a holds the ghosts of the union. False on an
// inconsistency (not expected: the caller then builds serially).
bool Stitch(Assembly& as, absl::Span<const Vec2> positions,
            const std::vector<uint8_t>& strip_of, uint8_t b,
            std::vector<uint32_t>* ghosts_a,
            const std::vector<uint32_t>& ghosts_b, const CancelToken* cancel,
            StripBuildStats* stats) {
  absl::flat_hash_map<uint64_t, uint32_t> open;  // unmatched half-edges
  std::vector<std::pair<uint32_t, uint32_t>> hull_edges;
  const std::vector<uint32_t>* old_ghosts[] = {ghosts_a, &ghosts_b};
  for (const std::vector<uint32_t>* ghosts : old_ghosts) {
    for (uint32_t t : *ghosts) {
      const uint32_t g = GhostBase(as.origin, t);
      if (g == kNoEdge) return false;
      const uint32_t r = as.twin[g];
      const uint32_t u = as.origin[r], v = as.origin[Next(r)];
      open.emplace(EdgeKey(u, v), r);
      hull_edges.emplace_back(u, v);
      as.Free(t);
    }
  }
  // Each hull vertex starts exactly one hull edge.
  Cdt cdt;
  absl::flat_hash_map<uint32_t, Cdt::Vertex_handle> handle;
  handle.reserve(hull_edges.size());
  Cdt::Face_handle hint;
  for (const auto& [u, v] : hull_edges) {
    const Vec2& p = positions[u];
    const Cdt::Vertex_handle h = cdt.insert(Kernel::Point_2(p.x, p.y), hint);
    h->info() = u;
    hint = h->face();
    handle[u] = h;
  }
  for (const auto& [u, v] : hull_edges) {
    const auto hu = handle.find(u), hv = handle.find(v);
    if (hu == handle.end() || hv == handle.end()) return false;
    cdt.insert_constraint(hu->second, hv->second);
  }
  if (cdt.dimension() < 2 || cdt.number_of_vertices() != hull_edges.size()) {
    return false;
  }
  std::vector<uint32_t> new_ghosts, seam;
  for (auto f = cdt.all_faces_begin(); f != cdt.all_faces_end(); ++f) {
    const bool infinite = cdt.is_infinite(f);
    if (!infinite) {
      int before = 0;
      for (int k = 0; k < 3; ++k) {
        before += strip_of[f->vertex(k)->info()] < b ? 1 : 0;
      }
      if (before == 0 || before == 3) continue;  // inside one side's hull
    }
    const uint32_t t = as.Allocate();
    for (int k = 0; k < 3; ++k) {
      const auto v = f->vertex(k);
      as.origin[3 * t + k] = cdt.is_infinite(v) ? kInfiniteVertex : v->info();
    }
    (infinite ? new_ghosts : seam).push_back(t);
  }
  if (!as.free.empty()) return false;
  for (const std::vector<uint32_t>* list : {&new_ghosts, &seam}) {
    for (uint32_t t : *list) {
      for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
        const uint32_t u = as.origin[e], v = as.origin[Next(e)];
        const auto it = open.find(EdgeKey(v, u));
        if (it != open.end()) {
          as.twin[e] = it->second;
          as.twin[it->second] = e;
          open.erase(it);
        } else if (!open.emplace(EdgeKey(u, v), e).second) {
          return false;
        }
      }
    }
  }
  if (!open.empty()) return false;
  stats->seam_triangles += seam.size();

  // Lawson: only edges with a new triangle on one side can be illegal; a
  // flip can make only the four edges around its quad illegal.
  const MeshView m = as.view();
  const Vec2* pos = positions.data();
  std::vector<uint32_t> stack;
  stack.reserve(3 * seam.size());
  for (uint32_t t : seam) {
    for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) stack.push_back(e);
  }
  uint64_t flips = 0;
  while (!stack.empty()) {
    const uint32_t e = stack.back();
    stack.pop_back();
    if (!rules::IsIllegal(m, pos, e)) continue;
    m.Flip(e);
    const uint32_t f = m.twin[e];
    stack.insert(stack.end(), {Next(e), Prev(e), Next(f), Prev(f)});
    if (++flips % (uint64_t{1} << 16) == 0 && cancel != nullptr &&
        cancel->Cancelled()) {
      return false;
    }
  }
  stats->seam_flips += flips;
  *ghosts_a = std::move(new_ghosts);
  return true;
}

}  // namespace

uint32_t DefaultStripCount(size_t num_sites) {
  const size_t threads =
      static_cast<size_t>(std::max(1, tbb::this_task_arena::max_concurrency()));
  if (threads == 1) return 1;
  const size_t by_size = num_sites / kMinSitesPerStrip;
  return static_cast<uint32_t>(std::max<size_t>(
      1, std::min({kStripsPerThread * threads, by_size, size_t{kMaxStrips}})));
}

Mesh BuildDelaunayInStrips(absl::Span<const Vec2> positions,
                           absl::Span<const uint32_t> sites, uint32_t strips,
                           const CancelToken* cancel, bool* cancelled,
                           StripBuildStats* stats) {
  StripBuildStats local_stats;
  if (stats == nullptr) stats = &local_stats;
  *stats = StripBuildStats();
  auto stop = [&] {
    if (cancel == nullptr || !cancel->Cancelled()) return false;
    if (cancelled != nullptr) *cancelled = true;
    return true;
  };
  auto serial = [&] {
    stats->strips = 1;
    return BuildDelaunayWithCgal(positions, sites, cancel, cancelled);
  };
  const size_t n = sites.size();
  strips = std::min(strips, kMaxStrips);
  if (strips < 2 || n < size_t{8} * strips) return serial();

  // Strip boundaries: lexicographic quantiles of an even sample (the sites
  // come in spatial order, so an even sample covers the set); each pivot is
  // a site and the first of its strip.
  const size_t sample_size = std::min(n, kPivotSample);
  std::vector<Vec2> sample(sample_size);
  for (size_t i = 0; i < sample_size; ++i) {
    sample[i] = positions[sites[i * n / sample_size]];
  }
  std::sort(sample.begin(), sample.end(), LexLess);
  std::vector<Vec2> pivot(strips - 1);
  for (uint32_t j = 1; j < strips; ++j) {
    pivot[j - 1] = sample[j * sample_size / strips];
  }
  std::vector<uint8_t> strip_of(positions.size(), 0);
  ParallelFor(0, n, [&](size_t i) {
    const uint32_t v = sites[i];
    strip_of[v] = static_cast<uint8_t>(
        std::upper_bound(pivot.begin(), pivot.end(), positions[v], LexLess) -
        pivot.begin());
  });

  // Each strip on its own thread, its sites in the order given.
  struct Strip {
    std::vector<uint32_t> origin, twin, ghosts;
    bool ok = false;
  };
  std::vector<Strip> part(strips);
  std::atomic<bool> any_cancelled{false};
  tbb::parallel_for(uint32_t{0}, strips, [&](uint32_t s) {
    std::vector<uint32_t> mine;
    for (uint32_t v : sites) {
      if (strip_of[v] == s) mine.push_back(v);
    }
    bool c = false;
    part[s].ok = TriangulateWithCgal(positions, mine, cancel, &c,
                                     &part[s].origin, &part[s].twin);
    if (c) any_cancelled = true;
  });
  if (any_cancelled || stop()) {
    if (cancelled != nullptr) *cancelled = true;
    return Mesh();
  }
  for (const Strip& s : part) {
    if (!s.ok) {
      stats->serial_fallback = true;
      return serial();
    }
  }

  // One set of arrays: strip s's slots shifted by the triangles before it.
  std::vector<size_t> first(strips + 1, 0);
  for (uint32_t s = 0; s < strips; ++s) {
    first[s + 1] = first[s] + part[s].origin.size();
  }
  Assembly as;
  // Each stitch adds two triangles: room for them, so that no append
  // moves the arrays.
  as.origin.reserve(first[strips] + size_t{6} * strips);
  as.twin.reserve(first[strips] + size_t{6} * strips);
  as.origin.resize(first[strips]);
  as.twin.resize(first[strips]);
  tbb::parallel_for(uint32_t{0}, strips, [&](uint32_t s) {
    Strip& p = part[s];
    const uint32_t shift = static_cast<uint32_t>(first[s]);
    for (size_t e = 0; e < p.origin.size(); ++e) {
      as.origin[first[s] + e] = p.origin[e];
      as.twin[first[s] + e] = p.twin[e] + shift;
    }
    for (size_t t = 0; t < p.origin.size() / 3; ++t) {
      const uint32_t* o = &p.origin[3 * t];
      if (o[0] == kInfiniteVertex || o[1] == kInfiniteVertex ||
          o[2] == kInfiniteVertex) {
        p.ghosts.push_back(static_cast<uint32_t>(t + shift / 3));
      }
    }
    std::vector<uint32_t>().swap(p.origin);
    std::vector<uint32_t>().swap(p.twin);
  });

  // Stitching costs time in the number of hull vertices: sets with many
  // points on their strips' hulls (points in convex position, on a few
  // curves) are built serially (a parabola of 20K points: 7 ms serially,
  // 337 ms in 2 strips).
  size_t hull_vertices = 0;
  for (const Strip& s : part) hull_vertices += s.ghosts.size();
  if (hull_vertices > std::max(kMaxHullVertices, n / kSitesPerHullVertex)) {
    stats->serial_fallback = true;
    std::vector<uint32_t>().swap(as.origin);
    std::vector<uint32_t>().swap(as.twin);
    return serial();
  }
  std::vector<uint32_t> ghosts = std::move(part[0].ghosts);
  for (uint32_t s = 1; s < strips; ++s) {
    if (stop()) return Mesh();
    if (!Stitch(as, positions, strip_of, static_cast<uint8_t>(s), &ghosts,
                part[s].ghosts, cancel, stats)) {
      if (stop()) return Mesh();
      stats->serial_fallback = true;
      return serial();
    }
  }
  if (stop()) return Mesh();
  stats->strips = strips;
  return Mesh(static_cast<uint32_t>(positions.size()), std::move(as.origin),
              std::move(as.twin), Mesh::Layout::kCanonical);
}

}  // namespace kinetri::core
