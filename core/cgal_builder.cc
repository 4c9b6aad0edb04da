// Initial / fallback Delaunay construction with CGAL, converted to our Mesh.
#include "core/cgal_builder.h"

#include <CGAL/Delaunay_triangulation_2.h>
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Triangulation_face_base_with_info_2.h>
#include <CGAL/Triangulation_vertex_base_with_info_2.h>

#include <algorithm>
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
  // own spatial sort of a range insertion would sort them again.
  Delaunay dt;
  Delaunay::Face_handle hint;
  for (size_t i = 0; i < sites.size(); ++i) {
    if (i % (size_t{1} << 15) == 0 && stop()) return false;
    const Vec2& p = positions[sites[i]];
    const Delaunay::Vertex_handle v = dt.insert(CgalPoint(p.x, p.y), hint);
    v->info() = sites[i];
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
