// Shared test helpers: point generators and the CGAL / brute-force oracles.
#ifndef KINETRI_TESTS_CORE_TEST_UTIL_H_
#define KINETRI_TESTS_CORE_TEST_UTIL_H_

#include <cstdint>
#include <random>
#include <utility>
#include <vector>

#include "core/triangulation.h"
#include "core/vec2.h"

namespace kinetri::testing {

using core::Vec2;
using EdgeList = std::vector<std::pair<Vec2, Vec2>>;

std::vector<Vec2> UniformPoints(size_t n, uint64_t seed, double scale = 1.0,
                                double offset = 0.0);
std::vector<Vec2> ClusteredPoints(size_t n, uint64_t seed);
// side x side integer lattice scaled by `spacing` (massively cocircular).
std::vector<Vec2> Lattice(int side, double spacing = 1.0);
std::vector<Vec2> Collinear(size_t n, uint64_t seed);
// Uniform points with every point repeated `copies` times.
std::vector<Vec2> WithDuplicates(size_t n, int copies, uint64_t seed);

// A limit a test asserts on time: `normal` in the normal build, `asan`
// under AddressSanitizer (2-3x slower), `tsan` under ThreadSanitizer
// (5-15x).
constexpr double BySanitizer(double normal, double asan, double tsan) {
#if defined(__SANITIZE_THREAD__)
  (void)normal, (void)asan;
  return tsan;
#elif defined(__SANITIZE_ADDRESS__)
  (void)normal, (void)tsan;
  return asan;
#else
  (void)asan, (void)tsan;
  return normal;
#endif
}

// Delaunay edges of the distinct positions, by CGAL; each pair lex-ordered.
EdgeList CgalDelaunayEdges(const std::vector<Vec2>& points);
// A dense batch of n Gaussian displacements (standard deviation sigma).
core::DisplacementBatch Brownian(size_t n, double sigma, std::mt19937_64& rng);
// The triangulation's edges as position pairs, in the same normal form.
EdgeList EdgesAsPositions(const core::Triangulation& t);
// The edges of triangles given as index triples into `points` (flat i, j,
// k, ...), in the same normal form.
EdgeList EdgesOfTriangles(const std::vector<Vec2>& points,
                          const std::vector<uint32_t>& triangles);

bool operator<(const Vec2& a, const Vec2& b);

// All point ids ranked from q in the order of queries.h (exact distance,
// nudged ties, then id), minus `self` (kNoVertex: none).
std::vector<uint32_t> BruteRank(const std::vector<Vec2>& pts, const Vec2& q,
                                uint32_t self);
// m query positions around the points' bounding box (a third of them
// exactly on points).
std::vector<Vec2> QueryPoints(const std::vector<Vec2>& pts, size_t m,
                              uint64_t seed);

}  // namespace kinetri::testing

#endif  // KINETRI_TESTS_CORE_TEST_UTIL_H_
