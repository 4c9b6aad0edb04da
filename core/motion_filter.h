// Vertex tolerances: which moving vertices can change nothing.
//
// After de Castro, Tournois, Alliez and Devillers, "Filtering relocations
// on a Delaunay triangulation" (SGP 2009). Every element whose validity a
// step must re-check gets a certificate, a distance h such that moving each
// of its vertices by less than h cannot change its answer:
//   - a finite triangle (a, b, c) stays positively oriented while each
//     vertex moves less than half its smallest altitude (three points within
//     that distance of a common line would fit in a strip narrower than the
//     triangle);
//   - an interior edge pq with apexes r and s stays strictly locally
//     Delaunay while each of the four moves less than half the width of an
//     annulus with p and q inside and r and s outside (centred where the
//     bisectors of pq and rs meet): a circle then still separates {p, q}
//     from {r, s}, so the lifted segment rs stays above pq where they
//     cross, and a non-convex quad's diagonal is always legal;
//   - a hull corner (the turn a ghost triangle checks) is a triangle of
//     three hull vertices.
// Each vertex u keeps a reference position ref(u) and a tolerance tol(u)
// with |ref(u) - c_E(u)| + tol(u) <= h_E for every element E it belongs to
// (c_E: the positions E was certified at). A vertex that moves to within
// tol(u) of ref(u), or does not move, is quiet; while every vertex of an
// element is quiet, the element is certified, so a step only has to look
// around the loud vertices. After the step the loud vertices are reset
// (ref = position) and every element they or the step's flips touched is
// certified again; a quiet vertex in such an element keeps the smaller of
// its tolerance and h - |position - ref|.
//
// The distances are computed in floating point and shrunk by a relative
// margin far above their rounding error, so a certificate never claims
// more than is true; the predicates stay exact, the filter only decides
// what they are asked.
#ifndef KINETRI_CORE_MOTION_FILTER_H_
#define KINETRI_CORE_MOTION_FILTER_H_

#include <cstdint>
#include <vector>

#include "core/flip_rules.h"
#include "core/mesh.h"
#include "core/vec2.h"

namespace kinetri::core {

// Each of a, b, c moving less than this keeps Orient2d(a, b, c) > 0; 0 if
// the orientation is not certainly positive.
double OrientTolerance(Vec2 a, Vec2 b, Vec2 c);

// Each of p, q, r, s moving less than this keeps edge pq (apexes r and s)
// strictly locally Delaunay, as long as both its triangles stay positively
// oriented; 0 if no such margin is certain.
double EdgeTolerance(Vec2 p, Vec2 q, Vec2 r, Vec2 s);

// Calls fn(vertex, h) for each vertex of each certificate that triangle
// slot t carries: its orientation (or, for a ghost, its hull corner) and
// the in-circle state of its interior edges, except those of its
// half-edges e with left_to_twin(e, twin(e)) (a pass over a set of
// triangles certifies each edge once that way). Free slots carry none.
template <typename Fn, typename Skip>
void ForEachCertificate(const MeshView& m, const Vec2* pos, uint32_t t, Fn&& fn,
                        Skip&& left_to_twin);

class MotionFilter {
 public:
  bool valid() const { return valid_; }
  void Invalidate() { valid_ = false; }

  // Resets every vertex at `pos` and certifies every element of `mesh`.
  void Certify(const Mesh& mesh, const std::vector<Vec2>& pos);

  // The vertices of `moved` that are loud for the positions `to`, in
  // increasing order if `moved` is.
  std::vector<uint32_t> Loud(const std::vector<uint32_t>& moved,
                             const std::vector<Vec2>& to) const;

  // After a step that looked only around `loud` (and whose mesh changes
  // all lie in triangles with changed[t] != 0, which include every triangle
  // around a loud vertex and the ghosts next to them): resets the loud
  // vertices at `pos` and certifies the elements of the changed triangles.
  void Recertify(const Mesh& mesh, const std::vector<Vec2>& pos,
                 const std::vector<uint32_t>& loud,
                 const std::vector<uint8_t>& changed);

  // The fraction of `moved` (sampled at most `samples`, evenly) whose move
  // from `from` to `to` is at least the tolerance a fresh certification at
  // `from` would give them: what a first filtered step would find loud.
  static double EstimateLoudFraction(const Mesh& mesh,
                                     const std::vector<Vec2>& from,
                                     const std::vector<Vec2>& to,
                                     const std::vector<uint32_t>& moved,
                                     uint32_t samples);

 private:
  std::vector<Vec2> ref_;
  std::vector<double> tol_;
  std::vector<uint8_t> reset_;  // scratch of Recertify, all zero between
  bool valid_ = false;
};

// --- implementation of the template ---

template <typename Fn, typename Skip>
void ForEachCertificate(const MeshView& m, const Vec2* pos, uint32_t t, Fn&& fn,
                        Skip&& left_to_twin) {
  const uint32_t a = m.origin[3 * t], b = m.origin[3 * t + 1],
                 c = m.origin[3 * t + 2];
  if (a == kNoVertex) return;
  if (m.IsGhost(t)) {
    // The corner this ghost checks (rules::TriangleOk); a collinear corner
    // gets 0, so any move of its three vertices is looked at.
    const uint32_t s = rules::SpokeOf(m, t);
    if (s == kNoEdge) return;
    const uint32_t p = rules::SpokePrev(m, s), v = m.origin[s],
                   q = rules::SpokeNext(m, s);
    if (p >= kInfiniteVertex || q >= kInfiniteVertex) return;
    const double h = OrientTolerance(pos[p], pos[v], pos[q]);
    fn(p, h);
    fn(v, h);
    fn(q, h);
    return;
  }
  const double h = OrientTolerance(pos[a], pos[b], pos[c]);
  fn(a, h);
  fn(b, h);
  fn(c, h);
  for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
    if (left_to_twin(e, m.twin[e])) continue;
    const uint32_t r = m.Apex(e), s = m.Across(e);
    if (s == kInfiniteVertex) continue;  // a hull edge is never illegal
    const uint32_t p = m.origin[e], q = m.Dest(e);
    const double he = EdgeTolerance(pos[p], pos[q], pos[r], pos[s]);
    fn(p, he);
    fn(q, he);
    fn(r, he);
    fn(s, he);
  }
}

}  // namespace kinetri::core

#endif  // KINETRI_CORE_MOTION_FILTER_H_
