// Predicates benchmark: Kinetri's exact Orient2d and InCircle against
// CGAL's (Exact_predicates_inexact_constructions_kernel: interval filter,
// then exact arithmetic), on the same point sets, signs cross-checked.
//
// Usage: kinetri-predicates-bench --quads=100000 --reps=5
// Three inputs: uniform random quadruples (the floating-point filters
// decide), cocircular and collinear quadruples on a scaled lattice (every
// call takes the exact path: the case of lattices and coincident motion),
// and quadruples perturbed by a few units in the last place of a cocircular
// one (the filters fail, the exact answers differ).
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <random>
#include <string>
#include <utility>
#include <vector>

#include "absl/flags/flag.h"
#include "core/predicates.h"
#include "core/program_flags.h"

ABSL_FLAG(uint32_t, quads, 100000, "quadruples of points per input");
ABSL_FLAG(int, reps, 5, "timed passes over each input (the median is shown)");
ABSL_FLAG(uint64_t, seed, 1, "random seed");

namespace {

using kinetri::core::Vec2;
using K = CGAL::Exact_predicates_inexact_constructions_kernel;
using Clock = std::chrono::steady_clock;

std::vector<Vec2> Uniform(size_t quads, std::mt19937_64& rng) {
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::vector<Vec2> p(4 * quads);
  for (Vec2& v : p) v = {u(rng), u(rng)};
  return p;
}

// Squares on a lattice of spacing 0.1 (not a dyadic number: the
// coordinates are rounded, the exact answers are those of the rounded
// values, mostly 0). No coordinate is 0, so that a few units in the last
// place stay within the predicates' exactness domain (no subnormals).
std::vector<Vec2> Cocircular(size_t quads, std::mt19937_64& rng) {
  std::uniform_int_distribution<int> u(1, 2000);
  std::vector<Vec2> p;
  p.reserve(4 * quads);
  const double s = 0.1;
  for (size_t i = 0; i < quads; ++i) {
    const int x = u(rng), y = u(rng), r = 1 + (u(rng) & 255);
    p.push_back({x * s, y * s});
    p.push_back({(x + r) * s, y * s});
    p.push_back({(x + r) * s, (y + r) * s});
    p.push_back({x * s, (y + r) * s});
  }
  return p;
}

std::vector<Vec2> Perturbed(size_t quads, std::mt19937_64& rng) {
  std::vector<Vec2> p = Cocircular(quads, rng);
  std::uniform_int_distribution<int> ulps(-3, 3);
  for (size_t i = 3; i < p.size(); i += 4) {
    for (int k = ulps(rng); k != 0; k += k > 0 ? -1 : 1) {
      p[i].x = std::nextafter(p[i].x, k > 0 ? 1e300 : -1e300);
    }
  }
  return p;
}

// Written with every timed pass's checksum, so no timed call can be
// optimised out.
volatile long g_sink = 0;

struct Result {
  double orient_ns;
  double incircle_ns;
  long checksum;           // sum of the timed calls' signs
  std::vector<int> signs;  // orient, then in-circle, of every quadruple
};

// Times orient over the first three points of each quadruple and incircle
// over all four (signs converted to int by the callers' functions).
template <typename Point, typename OrientFn, typename InCircleFn>
Result Time(const std::vector<Point>& p, int reps, OrientFn orient,
            InCircleFn incircle) {
  const size_t quads = p.size() / 4;
  std::vector<double> o_ns, i_ns;
  long checksum = 0;
  for (int r = 0; r < reps; ++r) {
    long s = 0;
    auto t0 = Clock::now();
    for (size_t i = 0; i < quads; ++i) {
      s += (i % 7 + 1) * orient(p[4 * i], p[4 * i + 1], p[4 * i + 2]);
    }
    auto t1 = Clock::now();
    for (size_t i = 0; i < quads; ++i) {
      s += (i % 5 + 1) * 3 *
           incircle(p[4 * i], p[4 * i + 1], p[4 * i + 2], p[4 * i + 3]);
    }
    auto t2 = Clock::now();
    o_ns.push_back(std::chrono::duration<double, std::nano>(t1 - t0).count() /
                   quads);
    i_ns.push_back(std::chrono::duration<double, std::nano>(t2 - t1).count() /
                   quads);
    checksum = s;
    g_sink = g_sink + s;  // the timed calls' results are used
  }
  std::sort(o_ns.begin(), o_ns.end());
  std::sort(i_ns.begin(), i_ns.end());
  // The signs, from an untimed pass, for the cross-check.
  std::vector<int> signs(2 * quads);
  for (size_t i = 0; i < quads; ++i) {
    signs[2 * i] = orient(p[4 * i], p[4 * i + 1], p[4 * i + 2]);
    signs[2 * i + 1] =
        incircle(p[4 * i], p[4 * i + 1], p[4 * i + 2], p[4 * i + 3]);
  }
  return {o_ns[o_ns.size() / 2], i_ns[i_ns.size() / 2], checksum,
          std::move(signs)};
}

}  // namespace

int main(int argc, char** argv) {
  kinetri::ParseProgramFlags(
      argc, argv,
      "Times Kinetri's exact Orient2d and InCircle against CGAL's (Epick) on "
      "uniform, cocircular and perturbed-cocircular quadruples, signs "
      "cross-checked; nanoseconds per call, median of --reps passes.");
  const size_t quads = absl::GetFlag(FLAGS_quads);
  const int reps = std::max(1, absl::GetFlag(FLAGS_reps));
  std::mt19937_64 rng(absl::GetFlag(FLAGS_seed));
  const K::Orientation_2 cgal_orient = K().orientation_2_object();
  const K::Side_of_oriented_circle_2 cgal_circle =
      K().side_of_oriented_circle_2_object();
  auto pt = [](const Vec2& v) { return K::Point_2(v.x, v.y); };
  struct Input {
    const char* name;
    std::vector<Vec2> points;
  };
  std::vector<Input> inputs;
  inputs.push_back({"uniform", Uniform(quads, rng)});
  inputs.push_back({"cocircular", Cocircular(quads, rng)});
  inputs.push_back({"perturbed", Perturbed(quads, rng)});
  std::printf("%-11s %-8s %12s %12s\n", "input", "engine", "orient_ns",
              "incircle_ns");
  int mismatches = 0;
  for (const Input& in : inputs) {
    const Result ours = Time(
        in.points, reps,
        [](const Vec2& a, const Vec2& b, const Vec2& c) {
          return kinetri::core::Orient2d(a, b, c);
        },
        [](const Vec2& a, const Vec2& b, const Vec2& c, const Vec2& d) {
          return kinetri::core::InCircle(a, b, c, d);
        });
    // CGAL's points are made once, outside the timed loops.
    std::vector<K::Point_2> cp;
    cp.reserve(in.points.size());
    for (const Vec2& v : in.points) cp.push_back(pt(v));
    const Result cgal = Time(
        cp, reps,
        [&](const K::Point_2& a, const K::Point_2& b, const K::Point_2& c) {
          return static_cast<int>(cgal_orient(a, b, c));
        },
        [&](const K::Point_2& a, const K::Point_2& b, const K::Point_2& c,
            const K::Point_2& d) {
          return static_cast<int>(cgal_circle(a, b, c, d));
        });
    std::printf("%-11s %-8s %12.1f %12.1f\n", in.name, "kinetri",
                ours.orient_ns, ours.incircle_ns);
    std::printf("%-11s %-8s %12.1f %12.1f\n", in.name, "cgal", cgal.orient_ns,
                cgal.incircle_ns);
    size_t differ = 0;
    for (size_t i = 0; i < ours.signs.size(); ++i) {
      differ += ours.signs[i] != cgal.signs[i];
    }
    if (differ != 0) {
      std::printf("MISMATCH on %s: %zu signs differ from CGAL's\n", in.name,
                  differ);
      ++mismatches;
    }
  }
  return mismatches == 0 ? 0 : 1;
}
