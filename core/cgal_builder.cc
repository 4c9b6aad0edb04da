// Initial / fallback Delaunay construction with CGAL, converted to our Mesh.
#include "core/cgal_builder.h"

#include <CGAL/Delaunay_triangulation_2.h>
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Triangulation_face_base_with_info_2.h>
#include <CGAL/Triangulation_vertex_base_with_info_2.h>

#include <algorithm>
#include <bit>
#include <utility>
#include <vector>

namespace kinetri::core {
namespace {
using Kernel = CGAL::Exact_predicates_inexact_constructions_kernel;
using Vb = CGAL::Triangulation_vertex_base_with_info_2<uint32_t, Kernel>;
using Fb = CGAL::Triangulation_face_base_with_info_2<uint32_t, Kernel>;
using Tds = CGAL::Triangulation_data_structure_2<Vb, Fb>;
using Delaunay = CGAL::Delaunay_triangulation_2<Kernel, Tds>;
using CgalPoint = Kernel::Point_2;

// The sites in rounds: a site goes to the last round with probability 1/2,
// to the one before with 1/4, and so on (by a hash of its id, so the order
// is deterministic), the first round holding about 64; each round keeps
// the order given.
std::vector<uint32_t> InsertionRounds(absl::Span<const uint32_t> sites) {
  int rounds = 1;
  while ((size_t{64} << rounds) < sites.size() && rounds < 24) ++rounds;
  auto round_of = [rounds](uint32_t id) {
    uint64_t h = id + 0x9E3779B97F4A7C15ull;  // splitmix64
    h = (h ^ (h >> 30)) * 0xBF58476D1CE4E5B9ull;
    h = (h ^ (h >> 27)) * 0x94D049BB133111EBull;
    h ^= h >> 31;
    const int zeros = h == 0 ? 64 : std::countr_zero(h);
    return std::max(0, rounds - 1 - zeros);
  };
  std::vector<uint32_t> start(static_cast<size_t>(rounds) + 1, 0);
  for (uint32_t s : sites) ++start[round_of(s) + 1];
  for (int r = 0; r < rounds; ++r) start[r + 1] += start[r];
  std::vector<uint32_t> order(sites.size());
  for (uint32_t s : sites) order[start[round_of(s)]++] = s;
  return order;
}
}  // namespace

bool TriangulateWithCgal(absl::Span<const Vec2> positions,
                         absl::Span<const uint32_t> sites,
                         const CancelToken* cancel, bool* cancelled,
                         std::vector<uint32_t>* origin_out,
                         std::vector<uint32_t>* twin_out) {
  auto stop = [&] {
    if (cancel == nullptr || !cancel->Cancelled()) return false;
    if (cancelled != nullptr) *cancelled = true;
    return true;
  };
  // One at a time, each located from the face of the one before: the sites
  // come in spatial order (internal ids follow a Hilbert curve), so CGAL's
  // own spatial sort of a range insertion would sort them again. They are
  // inserted in rounds (a biased randomized insertion order, Amenta, Choi
  // and Rote 2003), each round in the spatial order: one in a straight
  // spatial order, points along a convex curve put every new point outside
  // the hull next to the last and cost a quadratic number of flips (80K
  // points on a parabola in 2 strips: 2.3 s; in rounds: 55 ms).
  const std::vector<uint32_t> order = InsertionRounds(sites);
  Delaunay dt;
  Delaunay::Face_handle hint;
  for (size_t i = 0; i < order.size(); ++i) {
    if (i % (size_t{1} << 13) == 0 && stop()) return false;
    const Vec2& p = positions[order[i]];
    const Delaunay::Vertex_handle v = dt.insert(CgalPoint(p.x, p.y), hint);
    v->info() = order[i];
    hint = v->face();
  }
  if (stop()) return false;
  if (dt.dimension() < 2) return false;

  // Number every face (finite and infinite) and emit three half-edges each.
  std::vector<Delaunay::Face_handle> faces;
  for (auto f = dt.all_faces_begin(); f != dt.all_faces_end(); ++f) {
    f->info() = static_cast<uint32_t>(faces.size());
    faces.push_back(f);
  }
  const size_t num_he = faces.size() * 3;
  std::vector<uint32_t> origin(num_he), twin(num_he);
  for (size_t t = 0; t < faces.size(); ++t) {
    if (t % (size_t{1} << 20) == 0 && stop()) return false;
    const auto f = faces[t];
    for (int i = 0; i < 3; ++i) {
      const auto v = f->vertex(i);
      origin[3 * t + i] = dt.is_infinite(v) ? kInfiniteVertex : v->info();
      // Half-edge v_i -> v_{i+1} is opposite v_{i+2}; its neighbour g holds
      // the reverse edge opposite its vertex k = g->index(f), at slot k+1.
      const auto g = f->neighbor((i + 2) % 3);
      const int k = g->index(f);
      twin[3 * t + i] = 3 * g->info() + static_cast<uint32_t>((k + 1) % 3);
    }
  }
  *origin_out = std::move(origin);
  *twin_out = std::move(twin);
  return true;
}

Mesh BuildDelaunayWithCgal(absl::Span<const Vec2> positions,
                           absl::Span<const uint32_t> sites,
                           const CancelToken* cancel, bool* cancelled) {
  std::vector<uint32_t> origin, twin;
  if (!TriangulateWithCgal(positions, sites, cancel, cancelled, &origin,
                           &twin)) {
    return Mesh();
  }
  return Mesh(static_cast<uint32_t>(positions.size()), std::move(origin),
              std::move(twin), Mesh::Layout::kCanonical);
}

}  // namespace kinetri::core
