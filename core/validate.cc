// Triangulation::Validate: exact check of topology, geometry and Delaunay.
#include <atomic>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "core/flip_rules.h"
#include "core/kinetic.h"
#include "core/parallel.h"
#include "core/predicates.h"
#include "core/triangulation.h"

namespace kinetri::core {

absl::Status Triangulation::Validate() const {
  const uint32_t n = size();
  // Bookkeeping: id maps, sites, coincident-point chains.
  if (ext_of_int_.size() != n || int_of_ext_.size() != n || rep_.size() != n ||
      dup_next_.size() != n) {
    return absl::InternalError("array sizes disagree");
  }
  for (uint32_t i = 0; i < n; ++i) {
    if (ext_of_int_[i] >= n || int_of_ext_[ext_of_int_[i]] != i) {
      return absl::InternalError(absl::StrCat("id maps broken at ", i));
    }
    const uint32_t r = rep_[i];
    if (r >= n || rep_[r] != r || pos_[r] != pos_[i]) {
      return absl::InternalError(absl::StrCat("bad representative of ", i));
    }
    if (dup_next_[i] != kNoVertex && rep_[dup_next_[i]] != r) {
      return absl::InternalError(absl::StrCat("bad duplicate chain at ", i));
    }
  }
  // Each site's chain starts at its representative and holds all members.
  {
    std::vector<uint32_t> members(n, 0);
    for (uint32_t i = 0; i < n; ++i) ++members[rep_[i]];
    uint64_t walked = 0;
    for (uint32_t r : sites_) {
      uint32_t len = 0;
      for (uint32_t p = r; p != kNoVertex && len <= n; p = dup_next_[p]) ++len;
      if (len != members[r]) {
        return absl::InternalError(absl::StrCat("chain of site ", r, " has ",
                                                len, " points, expected ",
                                                members[r]));
      }
      walked += len;
    }
    if (walked != n) return absl::InternalError("points missing from chains");
  }
  uint32_t site_count = 0;
  for (uint32_t i = 0; i < n; ++i) site_count += rep_[i] == i;
  if (site_count != sites_.size()) {
    return absl::InternalError("site list out of date");
  }

  if (mesh_.empty()) {
    // Line mode: sites sorted along one line, all collinear, distinct.
    if (line_.size() != sites_.size()) {
      return absl::InternalError("line mode: wrong number of sites");
    }
    for (size_t r = 1; r < line_.size(); ++r) {
      if (!LexLess(pos_[line_[r - 1]], pos_[line_[r]])) {
        return absl::InternalError("line mode: sites not strictly ordered");
      }
      if (r >= 2 &&
          Orient2d(pos_[line_[0]], pos_[line_[1]], pos_[line_[r]]) != 0) {
        return absl::InternalError(
            "line mode but sites are not collinear (should be planar)");
      }
    }
    return absl::OkStatus();
  }

  const MeshView m = mesh_.view();
  const uint32_t ne = mesh_.num_half_edges();
  const auto& ve = mesh_.vertex_edge();
  const Vec2* p = pos_.data();
  std::atomic<int64_t> first_error{-1};
  std::atomic<int> error_kind{0};
  auto fail = [&](size_t where, int kind) {
    int64_t expected = -1;
    if (first_error.compare_exchange_strong(expected,
                                            static_cast<int64_t>(where))) {
      error_kind = kind;
    }
  };
  // Topology of every half-edge.
  ParallelFor(0, ne, [&](size_t i) {
    const uint32_t e = static_cast<uint32_t>(i);
    const uint32_t f = m.twin[e];
    if (f >= ne || f == e || m.twin[f] != e) return fail(e, 1);
    if (m.origin[f] != m.Dest(e) || m.Dest(f) != m.origin[e]) {
      return fail(e, 2);
    }
    const uint32_t o = m.origin[e];
    if (o != kInfiniteVertex && (o >= n || rep_[o] != o)) return fail(e, 3);
  });
  if (first_error >= 0) {
    static const char* kWhat[] = {"", "twin is not an involution",
                                  "twin endpoints do not match",
                                  "origin is not a site"};
    return absl::InternalError(absl::StrCat("half-edge ", first_error.load(),
                                            ": ", kWhat[error_kind.load()]));
  }
  // Vertex -> edge links and one fan per vertex (manifold).
  std::atomic<uint64_t> fan_total{0};
  ParallelFor(0, sites_.size(), [&](size_t k) {
    const uint32_t v = sites_[k];
    const uint32_t e0 = ve[v];
    if (e0 >= ne || m.origin[e0] != v) return fail(v, 4);
    uint32_t e = e0;
    uint64_t len = 0;
    do {
      ++len;
      e = m.twin[Prev(e)];
      if (len > ne) return fail(v, 5);
    } while (e != e0);
    fan_total += len;
  });
  if (first_error >= 0) {
    return absl::InternalError(
        absl::StrCat("vertex ", first_error.load(),
                     error_kind == 4 ? ": vertex_edge does not leave it"
                                     : ": fan does not close"));
  }
  uint64_t finite_origin = 0;
  for (uint32_t e = 0; e < ne; ++e)
    finite_origin += m.origin[e] != kInfiniteVertex;
  if (fan_total != finite_origin) {
    return absl::InternalError(
        "some vertex has more than one fan (mesh not a manifold)");
  }
  // Geometry: every triangle valid, hull winds once.
  ParallelFor(0, mesh_.num_triangles(), [&](size_t t) {
    if (!rules::TriangleOk(m, p, static_cast<uint32_t>(t))) fail(t, 6);
  });
  if (first_error >= 0) {
    return absl::InternalError(
        absl::StrCat("triangle ", first_error.load(),
                     " is not counter-clockwise (or its hull turn is reflex)"));
  }
  if (!KineticExecutor::HullWindsOnce(mesh_, pos_)) {
    return absl::InternalError("hull does not wind exactly once");
  }
  // Euler: finite triangles = 2V - H - 2.
  uint64_t ghosts = 0;
  for (uint32_t t = 0; t < mesh_.num_triangles(); ++t) ghosts += m.IsGhost(t);
  const uint64_t finite = mesh_.num_triangles() - ghosts;
  if (finite + ghosts + 2 != 2 * static_cast<uint64_t>(sites_.size())) {
    return absl::InternalError("Euler characteristic is wrong");
  }
  // Delaunay: every interior edge is locally Delaunay (exact, with SoS).
  ParallelFor(0, ne, [&](size_t i) {
    const uint32_t e = static_cast<uint32_t>(i);
    if (e < m.twin[e] && rules::IsIllegal(m, p, e)) fail(e, 7);
  });
  if (first_error >= 0) {
    return absl::InternalError(
        absl::StrCat("edge ", first_error.load(), " is not locally Delaunay"));
  }
  // What the next step trusts without looking: the region executor's kept
  // apexes, where it keeps them for this mesh.
  return region_executor_.CheckAcross(mesh_);
}

}  // namespace kinetri::core
