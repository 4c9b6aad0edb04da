// kinetri-scan-probe: what the dense scan of a kinetic step costs when the
// apex across each edge is read from the mesh (origin[Prev(twin[e])], a
// load in the neighbour's slot, as the region executor does today) and
// when it is read from a per-half-edge array beside the triangle's own
// vertices (core/mesh_scan.h, FillAcross). Both scans run over the same
// mesh and the same moved positions, in regions of triangle slots on all
// cores as the region executor cuts them, alternating; their answers must
// be equal (exit 1 otherwise). A third scan reads a list of each finite
// edge's four vertices, in slot order, and tests each edge once (the
// triangle scans test each from both sides): what a scan costs when
// neither the topology's loads nor a second evaluation of an edge remain.
// A fourth tests each edge once from the array: from the half-edge whose
// origin is the smaller vertex id, its quads batched four to a vector.
//
// Usage: kinetri-scan-probe --n=1000000 --sigma=0.01 --reps=15
#include <tbb/task_arena.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <random>
#include <vector>

#include "absl/flags/flag.h"
#include "core/flip_rules.h"
#include "core/mesh_scan.h"
#include "core/parallel.h"
#include "core/predicates.h"
#include "core/program_flags.h"
#include "core/triangulation.h"

ABSL_FLAG(uint32_t, n, 1000000, "uniform random points in the unit square");
ABSL_FLAG(double, sigma, 0.01,
          "Brownian displacement per coordinate, in mean spacings");
ABSL_FLAG(int, reps, 15, "timed repetitions of each scan");
ABSL_FLAG(uint32_t, region_triangles, 8192,
          "triangle slots per region (the region executor's default)");
ABSL_FLAG(uint64_t, seed, 1, "random seed");

namespace {

namespace kc = kinetri::core;
using kc::Vec2;

double Ms(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(
             std::chrono::steady_clock::now() - t0)
      .count();
}

// An edge e (e < twin(e) in the edge list) and its quad: origin a, destination
// b, apex c of its own triangle, apex d across.
struct Quad {
  uint32_t a, b, c, d, e;
};
using Lanes = double __attribute__((vector_size(32)));

// Compiled as core/mesh_scan.cc compiles the scan: an AVX2 clone picked at
// load time where the compiler and target allow it, so that the three
// scans are compared on the same vector units.
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && \
    !defined(__SANITIZE_ADDRESS__) && !defined(__SANITIZE_THREAD__)
#define KINETRI_PROBE_CLONES __attribute__((target_clones("avx2", "default")))
#else
#define KINETRI_PROBE_CLONES
#endif

// Appends the edges of q[lo, hi) that rules::IsIllegal finds illegal:
// Shewchuk's in-circle filter for four edges in the lanes of one vector,
// the exact predicate where it cannot decide.
KINETRI_PROBE_CLONES void ScanQuads(const Quad* q, size_t lo, size_t hi,
                                    const Vec2* p, std::vector<uint32_t>* out) {
  auto exact = [&](const Quad& x) {
    if (kc::InCircleSoS(p[x.a], p[x.b], p[x.c], p[x.d]) > 0) {
      out->push_back(x.e);
    }
  };
  size_t i = lo;
  for (; i + 4 <= hi; i += 4) {
    Lanes adx, ady, bdx, bdy, cdx, cdy;
    for (int k = 0; k < 4; ++k) {
      const Quad& x = q[i + k];
      const Vec2 a = p[x.a], b = p[x.b], c = p[x.c], d = p[x.d];
      adx[k] = a.x - d.x;
      ady[k] = a.y - d.y;
      bdx[k] = b.x - d.x;
      bdy[k] = b.y - d.y;
      cdx[k] = c.x - d.x;
      cdy[k] = c.y - d.y;
    }
    const Lanes bc = bdx * cdy, cb = cdx * bdy, ca = cdx * ady, ac = adx * cdy,
                ab = adx * bdy, ba = bdx * ady;
    const Lanes alift = adx * adx + ady * ady;
    const Lanes blift = bdx * bdx + bdy * bdy;
    const Lanes clift = cdx * cdx + cdy * cdy;
    const Lanes det = alift * (bc - cb) + blift * (ca - ac) + clift * (ab - ba);
    const Lanes zero = {0, 0, 0, 0};
    const Lanes abc = bc < zero ? -bc : bc, acb = cb < zero ? -cb : cb;
    const Lanes aca = ca < zero ? -ca : ca, aac = ac < zero ? -ac : ac;
    const Lanes aab = ab < zero ? -ab : ab, aba = ba < zero ? -ba : ba;
    const Lanes permanent =
        (abc + acb) * alift + (aca + aac) * blift + (aab + aba) * clift;
    const auto legal = -det > kc::internal::kIccErrBoundA * permanent;
    for (int k = 0; k < 4; ++k) {
      if (!legal[k]) exact(q[i + k]);
    }
  }
  for (; i < hi; ++i) exact(q[i]);
}

struct Found {
  std::vector<uint32_t> invalid, illegal;
  std::vector<Quad> batch;  // the edge-once array scan's quads to test
};

// Calls scan(region, lo, hi, &found[region]) for every region, in parallel.
template <typename Scan>
double TimeScan(uint32_t nt, uint32_t rt, std::vector<Found>& found,
                Scan&& scan) {
  const auto t0 = std::chrono::steady_clock::now();
  kc::ParallelFor(
      0, found.size(),
      [&](size_t r) {
        Found& f = found[r];
        f.invalid.clear();
        f.illegal.clear();
        const uint32_t lo = static_cast<uint32_t>(r) * rt;
        scan(lo, std::min(nt, lo + rt), &f);
      },
      1);
  return Ms(t0);
}

void Print(const char* name, std::vector<double> ms) {
  std::sort(ms.begin(), ms.end());
  std::printf("%-28s best %7.2f  median %7.2f ms\n", name, ms.front(),
              ms[ms.size() / 2]);
}

}  // namespace

int main(int argc, char** argv) {
  kinetri::ParseProgramFlags(
      argc, argv,
      "Times the dense scan of a kinetic step (invalid triangles, illegal "
      "edges) with the apexes across read from the mesh, from a "
      "per-half-edge array, from an edge list tested once per edge, and "
      "from the array tested once per edge, on the same moved points; "
      "exits 1 unless all four agree.");
  const uint32_t n = absl::GetFlag(FLAGS_n);
  const int reps = std::max(1, absl::GetFlag(FLAGS_reps));
  const uint32_t rt =
      std::clamp(absl::GetFlag(FLAGS_region_triangles), 1u, 1u << 24);
  std::mt19937_64 rng(absl::GetFlag(FLAGS_seed));
  std::uniform_real_distribution<double> u(0, 1);
  std::vector<Vec2> start(n);
  for (Vec2& p : start) p = {u(rng), u(rng)};
  auto t = kc::Triangulation::Create(start);
  if (!t.ok()) {
    std::fprintf(stderr, "%s\n", t.status().ToString().c_str());
    return 1;
  }
  // The mesh in the triangulation's spatial order, and every vertex moved
  // as a Brownian step of the benchmarks moves it.
  const kc::TriangulationView v = t->view();
  const kc::MeshView& m = v.mesh;
  const uint32_t nt = m.num_half_edges / 3;
  std::vector<Vec2> to(v.pos, v.pos + v.num_points);
  std::normal_distribution<double> g(
      0, absl::GetFlag(FLAGS_sigma) / std::sqrt(double(n)));
  for (Vec2& p : to) p = {p.x + g(rng), p.y + g(rng)};
  const Vec2* pos = to.data();

  std::vector<uint32_t> across(m.num_half_edges);
  const size_t regions = (size_t{nt} + rt - 1) / rt;
  // Each region's finite edges, in slot order.
  std::vector<Quad> quads;
  std::vector<size_t> quads_at(regions + 1, 0);
  for (uint32_t e = 0; e < m.num_half_edges; ++e) {
    if (e % (3 * rt) == 0) quads_at[e / (3 * rt)] = quads.size();
    const Quad x{m.origin[e], m.Dest(e), m.Apex(e), 0, e};
    if (m.IsFree(e / 3) || e > m.twin[e] || x.a >= kc::kInfiniteVertex ||
        x.b >= kc::kInfiniteVertex || x.c >= kc::kInfiniteVertex ||
        m.Across(e) >= kc::kInfiniteVertex) {
      continue;
    }
    quads.push_back(x);
    quads.back().d = m.Across(e);
  }
  quads_at[regions] = quads.size();
  std::vector<Found> by_mesh(regions), by_array(regions), filled(regions),
      by_quads(regions), by_once(regions);
  std::vector<double> t_mesh, t_array, t_fill, t_quads, t_once;
  // Whether slot t holds a finite triangle; an invalid one is appended
  // to f->invalid (ghosts are decided and skipped here).
  auto finite_triangle = [&](uint32_t t, Found* f) {
    if (m.IsFree(t)) return false;
    const bool ghost = m.IsGhost(t);
    const uint32_t* o = m.origin + 3 * t;
    if (ghost ? !kc::rules::TriangleOk(m, pos, t)
              : kc::Orient2d(pos[o[1]], pos[o[2]], pos[o[0]]) <= 0) {
      f->invalid.push_back(t);
    }
    return !ghost;
  };
  for (int i = 0; i < reps; ++i) {
    t_mesh.push_back(
        TimeScan(nt, rt, by_mesh, [&](uint32_t lo, uint32_t hi, Found* f) {
          kc::ScanTriangles(m, pos, lo, hi, &f->invalid, &f->illegal);
        }));
    t_fill.push_back(
        TimeScan(nt, rt, filled, [&](uint32_t lo, uint32_t hi, Found*) {
          kc::FillAcross(m, lo, hi, across.data());
        }));
    t_array.push_back(
        TimeScan(nt, rt, by_array, [&](uint32_t lo, uint32_t hi, Found* f) {
          kc::ScanTriangles(m, pos, across.data(), lo, hi, &f->invalid,
                            &f->illegal);
        }));
    // Orientation of each finite triangle, then each edge once.
    t_quads.push_back(
        TimeScan(nt, rt, by_quads, [&](uint32_t lo, uint32_t hi, Found* f) {
          for (uint32_t t = lo; t < hi; ++t) {
            finite_triangle(t, f);
          }
          ScanQuads(quads.data(), quads_at[lo / rt], quads_at[lo / rt + 1], pos,
                    &f->illegal);
        }));
    // The design the edge list bounds: origin and across in slot order,
    // each edge tested once from the half-edge whose origin is the smaller
    // vertex id (no twin needed), its quads batched four to a vector.
    t_once.push_back(
        TimeScan(nt, rt, by_once, [&](uint32_t lo, uint32_t hi, Found* f) {
          constexpr size_t kBatch = 256;
          f->batch.clear();
          for (uint32_t t = lo; t < hi; ++t) {
            if (!finite_triangle(t, f)) continue;
            const uint32_t* o = m.origin + 3 * t;
            const uint32_t* x = across.data() + 3 * t;
            for (uint32_t k = 0; k < 3; ++k) {
              const uint32_t a = o[k], b = o[(k + 1) % 3];
              if (a < b && x[k] < kc::kInfiniteVertex) {
                f->batch.push_back({a, b, o[(k + 2) % 3], x[k], 3 * t + k});
              }
            }
            if (f->batch.size() >= kBatch) {
              ScanQuads(f->batch.data(), 0, f->batch.size(), pos, &f->illegal);
              f->batch.clear();
            }
          }
          ScanQuads(f->batch.data(), 0, f->batch.size(), pos, &f->illegal);
        }));
  }
  // Its edges named as the other scans name them (e < twin(e)), in order;
  // an edge may be found from the triangle in the next region, so the
  // whole list is compared.
  std::vector<uint32_t> once_illegal, mesh_illegal;
  for (size_t r = 0; r < regions; ++r) {
    for (uint32_t e : by_once[r].illegal) {
      once_illegal.push_back(std::min(e, m.twin[e]));
    }
    mesh_illegal.insert(mesh_illegal.end(), by_mesh[r].illegal.begin(),
                        by_mesh[r].illegal.end());
  }
  std::sort(once_illegal.begin(), once_illegal.end());
  size_t differ = once_illegal != mesh_illegal;
  size_t invalid = 0, illegal = 0;
  for (size_t r = 0; r < regions; ++r) {
    invalid += by_mesh[r].invalid.size();
    illegal += by_mesh[r].illegal.size();
    differ += by_mesh[r].invalid != by_array[r].invalid ||
              by_mesh[r].illegal != by_array[r].illegal ||
              by_mesh[r].invalid != by_quads[r].invalid ||
              by_mesh[r].illegal != by_quads[r].illegal ||
              by_mesh[r].invalid != by_once[r].invalid;
  }
  std::printf(
      "n=%u sigma=%g triangles=%u regions=%zu threads=%d: %zu invalid "
      "triangles, %zu illegal edges, %zu disagreements\n",
      n, absl::GetFlag(FLAGS_sigma), nt, regions,
      tbb::this_task_arena::max_concurrency(), invalid, illegal, differ);
  Print("scan, apexes from the mesh", t_mesh);
  Print("scan, apexes from the array", t_array);
  Print("FillAcross (whole mesh)", t_fill);
  Print("edge list, each edge once", t_quads);
  Print("array, each edge once", t_once);
  return differ == 0 ? 0 : 1;
}
