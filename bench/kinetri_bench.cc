// kinetri-bench: cost per simulation step of Kinetri and its peers (CGAL
// rebuild, CGAL move(), a uniform grid, nanoflann), on moving points, in one
// process.
//
//   kinetri-bench --quick                 # N up to 100K, a few steps
//   kinetri-bench --json=out.json         # full matrix, JSON records
//
// For every workload and N, each engine runs the same steps; phases are timed
// separately (update/rebuild, all-points NN, all-points 8-NN, radius with a
// typical 8 and 32 neighbours, NN and radius of arbitrary query points). On
// the first measured step all engines' answers are compared (squared
// distances, radius counts, Delaunay edge sets for the CGAL engines); an
// engine that disagrees is reported as FAILED and not timed.
#include <CGAL/Delaunay_triangulation_2.h>
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Triangulation_vertex_base_with_info_2.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <functional>
#include <map>
#include <memory>
#include <nanoflann.hpp>
#include <random>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "absl/flags/flag.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "bench/device_grid.h"
#include "bench/grid_engine.h"
#include "bench/nanoflann_cloud.h"
#ifdef KINETRI_BENCH_CUDA
#include "core/device/cuda_backend.h"
#endif
#include "core/parallel.h"
#include "core/program_flags.h"
#include "core/queries.h"
#include "core/triangulation.h"

ABSL_FLAG(bool, quick, false,
          "reduced matrix: N = 10K, 100K; 3 steps; 3 s per engine");
ABSL_FLAG(std::string, json, "", "write the records to this JSON file");
ABSL_FLAG(std::string, sizes, "", "comma-separated N (overrides defaults)");
ABSL_FLAG(std::string, workloads, "paper,brownian,shear,vortex,clustered",
          "comma-separated workloads");
ABSL_FLAG(int, steps, 0,
          "measured steps after a warm-up (0: 3 quick, 20 full)");
ABSL_FLAG(double, engine_budget_s, 0,
          "stop timing an engine on a workload/N once its measured time "
          "passes this many seconds (0: 3 quick, 90 full); its record then "
          "says how many steps it ran");
ABSL_FLAG(int, query_points, 100000, "arbitrary query points per step");
ABSL_FLAG(bool, recycle_answers, true,
          "Kinetri builds each step's query answers in the memory of the "
          "last step's (core::RowOptions::recycle), as the peers write into "
          "buffers allocated before their timers");
ABSL_FLAG(std::string, radius_plan, "auto",
          "how Kinetri's radius queries find the sites of a disk: auto (by "
          "the expected sites per disk), graph (walk the Delaunay graph) or "
          "cells (a cell index of side r built per query batch)");
ABSL_FLAG(int64_t, device_loop_capacity, -1,
          "kinetri-device: the worklist size below which legalizing rounds "
          "run in device loops without the host (core::device::LoopControl; "
          "0: the host drives every round; -1: the backend's default)");
ABSL_FLAG(int64_t, device_loop_rounds, -1,
          "kinetri-device: rounds a device loop runs between two reads of "
          "its state by the host (-1: the backend's default)");
ABSL_FLAG(std::string, engines, "",
          "comma-separated engines to run (default: all of kinetri, "
          "kinetri-1t, kinetri-rounds, kinetri-device, cgal-rebuild, "
          "cgal-move, grid, grid-device, nanoflann; kinetri-rounds is the "
          "round executor on all threads, kinetri-device the device "
          "executor (on a GPU when built with CUDA and one is present, else "
          "its emulated backend on CPU threads: not a speed claim: update, "
          "all-NN and the queries), kinetri-1t and kinetri-rounds update "
          "and all-NN only; grid-device a uniform grid on the same "
          "device backend as kinetri-device, sort + all-NN)");

#ifndef KINETRI_DEVICE_EMULATED
// Without the CCCL headers there is no device grid (nor device executor).
std::unique_ptr<kinetri::bench::DeviceGrid> kinetri::bench::MakeDeviceGrid(
    kinetri::core::device::DeviceBackend) {
  return nullptr;
}
#endif

namespace {

using kinetri::core::Vec2;
using Clock = std::chrono::steady_clock;
namespace kc = kinetri::core;

double Ms(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

struct Workload {
  std::string name;
  double param;
  std::vector<Vec2> start;
  // Displacements of step s (depends on the current positions).
  std::function<std::vector<Vec2>(const std::vector<Vec2>&, int)> motion;
};

Workload MakeWorkload(const std::string& name, double param, size_t n,
                      uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(0, 1);
  const double spacing = 1.0 / std::sqrt(double(n));
  Workload w{name, param, std::vector<Vec2>(n), {}};
  if (name == "paper") {
    // The research note's DLA benchmark as its code runs it: box of side
    // 1e4, half of the particles (the aggregate) never move, the other half
    // move at a constant velocity of `param` per step in a random direction.
    // Kept in double precision, so the motion is real (see REFERENCES.md).
    for (auto& p : w.start) p = {1e4 * u(rng), 1e4 * u(rng)};
    std::vector<Vec2> vel(n, Vec2{0, 0});
    for (size_t i = 1; i < n; i += 2) {
      const double a = 2 * M_PI * u(rng);
      vel[i] = {param * std::cos(a), param * std::sin(a)};
    }
    w.motion = [vel](const std::vector<Vec2>&, int) { return vel; };
    return w;
  }
  if (name == "clustered") {
    // 90% of the points in 18 tight Gaussian clusters (points i with
    // i % 10 != 0 go to centre i % 20, so centres 0 and 10 stay unused),
    // 10% uniform: about 5000x density contrast at the cluster cores.
    std::vector<Vec2> centers(20);
    for (auto& c : centers) c = {0.1 + 0.8 * u(rng), 0.1 + 0.8 * u(rng)};
    std::normal_distribution<double> g(0, 0.004);
    for (size_t i = 0; i < n; ++i) {
      if (i % 10 == 0) {
        w.start[i] = {u(rng), u(rng)};
      } else {
        const Vec2 c = centers[i % 20];
        w.start[i] = {c.x + g(rng), c.y + g(rng)};
      }
    }
  } else {
    for (auto& p : w.start) p = {u(rng), u(rng)};
  }
  auto gen = std::make_shared<std::mt19937_64>(seed + 1);
  if (name == "brownian" || name == "clustered") {
    const double sigma = param * spacing;
    w.motion = [gen, sigma](const std::vector<Vec2>& cur, int) {
      std::normal_distribution<double> g(0, sigma);
      std::vector<Vec2> d(cur.size());
      for (auto& v : d) v = {g(*gen), g(*gen)};
      return d;
    };
  } else if (name == "shear") {  // u = rate * (y - 1/2), x only
    const double rate = param * spacing;
    w.motion = [rate](const std::vector<Vec2>& cur, int) {
      std::vector<Vec2> d(cur.size());
      for (size_t i = 0; i < cur.size(); ++i)
        d[i] = {rate * (cur[i].y - 0.5), 0};
      return d;
    };
  } else {  // vortex: rigid-ish rotation about the centre, decaying outward
    const double omega = param * spacing;
    w.motion = [omega](const std::vector<Vec2>& cur, int) {
      std::vector<Vec2> d(cur.size());
      for (size_t i = 0; i < cur.size(); ++i) {
        const double x = cur[i].x - 0.5, y = cur[i].y - 0.5;
        const double f = omega / (0.05 + x * x + y * y);
        d[i] = {-y * f * 0.05, x * f * 0.05};
      }
      return d;
    };
  }
  return w;
}

using kinetri::bench::NanoCloud;
using kinetri::bench::NanoTree;

// Answers of one engine for the cross-check: per point, the squared
// distances of its k nearest others and its radius counts; per query point,
// the squared distances to its nearest and 8 nearest points and its radius
// count; for the
// CGAL engines, the Delaunay edge set.
struct Answers {
  std::vector<double> nn_d2, knn_d2, qnn_d2, qknn_d2;
  std::vector<uint64_t> r8_count, r32_count, qr8_count;
  std::vector<std::pair<uint32_t, uint32_t>> edges;
};

double D2(const Vec2& a, const Vec2& b) {
  const double dx = a.x - b.x, dy = a.y - b.y;
  return dx * dx + dy * dy;
}

struct Record {
  std::string workload;
  double param;
  size_t n;
  std::string engine;
  int threads;
  std::string phase;
  double median_ms, p90_ms;
  int steps;
};

double Quantile(std::vector<double> v, double q) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  return v[std::min(v.size() - 1,
                    static_cast<size_t>(q * (v.size() - 1) + 0.5))];
}

using K = CGAL::Exact_predicates_inexact_constructions_kernel;
using Vb = CGAL::Triangulation_vertex_base_with_info_2<uint32_t, K>;
using Tds = CGAL::Triangulation_data_structure_2<Vb>;
using CgalDt = CGAL::Delaunay_triangulation_2<K, Tds>;

std::unique_ptr<CgalDt> CgalBuild(const std::vector<Vec2>& pos) {
  std::vector<std::pair<K::Point_2, uint32_t>> p;
  p.reserve(pos.size());
  for (uint32_t i = 0; i < pos.size(); ++i)
    p.emplace_back(K::Point_2(pos[i].x, pos[i].y), i);
  return std::make_unique<CgalDt>(p.begin(), p.end());  // spatially sorted
}

std::vector<std::pair<uint32_t, uint32_t>> CgalEdges(const CgalDt& dt) {
  std::vector<std::pair<uint32_t, uint32_t>> e;
  for (auto it = dt.finite_edges_begin(); it != dt.finite_edges_end(); ++it) {
    const uint32_t a = it->first->vertex(CgalDt::cw(it->second))->info();
    const uint32_t b = it->first->vertex(CgalDt::ccw(it->second))->info();
    e.emplace_back(std::min(a, b), std::max(a, b));
  }
  std::sort(e.begin(), e.end());
  return e;
}

// The commit checked out in the source tree the binary was built from, read
// when the run starts ("-dirty" when it had uncommitted changes).
std::string SourceCommit() {
  std::string commit = "unknown";
  const std::string git =
      absl::StrCat("git -C '", KINETRI_SOURCE_DIR,
                   "' describe --always --dirty --abbrev=7 2>/dev/null");
  if (FILE* f = popen(git.c_str(), "r")) {
    char buf[64] = {0};
    if (fgets(buf, sizeof buf, f))
      commit = std::string(buf, strcspn(buf, "\n"));
    pclose(f);
  }
  return commit;
}

std::string MachineJson(const std::string& commit) {
  std::ifstream cpu("/proc/cpuinfo");
  std::string line, model = "unknown";
  while (std::getline(cpu, line)) {
    if (line.rfind("model name", 0) == 0) {
      model = line.substr(line.find(':') + 2);
      break;
    }
  }
  return absl::StrCat("{\"cpu\":\"", model,
                      "\",\"cores\":", std::thread::hardware_concurrency(),
                      ",\"gpu\":null,\"commit\":\"", commit, "\"}");
}

}  // namespace

int main(int argc, char** argv) {
  kinetri::ParseProgramFlags(
      argc, argv,
      "Benchmarks Kinetri against CGAL (rebuild and move()), a uniform grid "
      "and nanoflann on moving points, all in one process: per-phase median "
      "and p90 milliseconds per step, answers cross-checked on the first "
      "step.\n  kinetri-bench --quick            N = 10K, 100K (< 1 min)\n"
      "  kinetri-bench --json=out.json    N = 10K, 100K, 1M, 20 steps\n"
      "Workloads: paper (the note's DLA set-up), brownian 0.01/0.1/1 "
      "spacings, shear, vortex, clustered.");
#ifdef KINETRI_BENCH_CUDA
  kc::device::RegisterCudaBackend();
#endif
  const std::string commit = SourceCommit();
  const bool quick = absl::GetFlag(FLAGS_quick);
  std::vector<size_t> sizes = quick
                                  ? std::vector<size_t>{10000, 100000}
                                  : std::vector<size_t>{10000, 100000, 1000000};
  if (!absl::GetFlag(FLAGS_sizes).empty()) {
    sizes.clear();
    for (auto s : absl::StrSplit(absl::GetFlag(FLAGS_sizes), ',')) {
      sizes.push_back(std::stoull(std::string(s)));
    }
  }
  const int steps = absl::GetFlag(FLAGS_steps) > 0 ? absl::GetFlag(FLAGS_steps)
                                                   : (quick ? 3 : 20);
  const double budget_ms = 1000.0 * (absl::GetFlag(FLAGS_engine_budget_s) > 0
                                         ? absl::GetFlag(FLAGS_engine_budget_s)
                                         : (quick ? 3.0 : 90.0));
  const size_t num_queries =
      static_cast<size_t>(std::max(0, absl::GetFlag(FLAGS_query_points)));
  kc::RowOptions::Plan radius_plan = kc::RowOptions::Plan::kAuto;
  if (absl::GetFlag(FLAGS_radius_plan) == "graph") {
    radius_plan = kc::RowOptions::Plan::kGraph;
  } else if (absl::GetFlag(FLAGS_radius_plan) == "cells") {
    radius_plan = kc::RowOptions::Plan::kCells;
  } else if (absl::GetFlag(FLAGS_radius_plan) != "auto") {
    std::fprintf(stderr, "--radius_plan must be auto, graph or cells\n");
    return 2;
  }
  std::set<std::string> engines = {
      "kinetri",        "kinetri-1t",   "kinetri-rounds",
      "kinetri-device", "cgal-rebuild", "cgal-move",
      "grid",           "grid-device",  "nanoflann"};
  if (!absl::GetFlag(FLAGS_engines).empty()) {
    std::set<std::string> want;
    for (auto e : absl::StrSplit(absl::GetFlag(FLAGS_engines), ',')) {
      if (!engines.count(std::string(e))) {
        std::fprintf(stderr, "unknown engine '%s'\n", std::string(e).c_str());
        return 2;
      }
      want.insert(std::string(e));
    }
    want.insert("kinetri");  // the reference of the cross-check
    engines = want;
  }
  std::vector<std::pair<std::string, double>> loads;
  for (auto w : absl::StrSplit(absl::GetFlag(FLAGS_workloads), ',')) {
    const std::string name(w);
    if (name == "brownian") {
      for (double s : {0.01, 0.1, 1.0}) loads.push_back({name, s});
    } else if (name == "paper") {
      loads.push_back({name, 5e-4});
    } else if (name == "shear" || name == "vortex") {
      loads.push_back({name, 0.5});
    } else if (name == "clustered") {
      loads.push_back({name, 0.1});
    } else {
      std::fprintf(stderr, "unknown workload '%s'\n", name.c_str());
      return 2;
    }
  }
  const int threads = static_cast<int>(std::thread::hardware_concurrency());
  const auto run_start = Clock::now();
  std::vector<Record> records;
  bool any_failed = false;
  std::printf("%-10s %6s %8s %-13s %-14s %10s %10s %5s\n", "workload", "param",
              "n", "engine", "phase", "median_ms", "p90_ms", "steps");
  for (const auto& [wname, param] : loads) {
    for (size_t n : sizes) {
      Workload w = MakeWorkload(wname, param, n, 12345);
      // Radii giving a typical 8 and 32 neighbours on this point set: the
      // median distance to the 8th / 32nd neighbour over a sample (for
      // clustered sets the uniform-density formula would give thousands).
      double r8 = 0, r32 = 0;
      Vec2 lo = w.start[0], hi = w.start[0];
      {
        NanoCloud cloud{&w.start};
        NanoTree tree(2, cloud, nanoflann::KDTreeSingleIndexAdaptorParams(10));
        std::vector<double> d8, d32;
        for (size_t k = 0; k < std::min<size_t>(n, 1000); ++k) {
          const size_t i = (k * 7919 + 13) % n;  // spread over all ids
          uint32_t idx[33];
          double dd[33];
          const double q[2] = {w.start[i].x, w.start[i].y};
          tree.knnSearch(q, 33, idx, dd);
          d8.push_back(dd[8]);
          d32.push_back(dd[32]);
        }
        // Nudged off the sampled distances so that no pair lies exactly on
        // the circle (engines legitimately differ on < vs <= there).
        r8 = std::sqrt(Quantile(d8, 0.5)) * (1 + 0x1p-20);
        r32 = std::sqrt(Quantile(d32, 0.5)) * (1 + 0x1p-20);
        for (const Vec2& p : w.start) {
          lo = {std::min(lo.x, p.x), std::min(lo.y, p.y)};
          hi = {std::max(hi.x, p.x), std::max(hi.y, p.y)};
        }
      }
      // Arbitrary query points: uniform over the points' bounding box.
      std::vector<Vec2> qs(num_queries);
      {
        std::mt19937_64 qrng(777);
        std::uniform_real_distribution<double> u(0, 1);
        for (auto& q : qs)
          q = {lo.x + (hi.x - lo.x) * u(qrng), lo.y + (hi.y - lo.y) * u(qrng)};
      }
      std::map<std::string, std::map<std::string, std::vector<double>>> times;
      std::map<std::string, double> spent;
      std::map<std::string, bool> failed, stopped;
      auto on = [&](const std::string& e) {
        return engines.count(e) && !failed[e] && !stopped[e];
      };
      std::unique_ptr<kc::Triangulation> tri, tri1, tri_rounds, tri_device;
      {
        auto t = kc::Triangulation::Create(w.start);
        tri = std::make_unique<kc::Triangulation>(*std::move(t));
        if (engines.count("kinetri-1t")) {
          kc::TriangulationOptions one;
          one.num_threads = 1;
          auto t1 = kc::Triangulation::Create(w.start, one);
          tri1 = std::make_unique<kc::Triangulation>(*std::move(t1));
        }
        if (engines.count("kinetri-rounds")) {
          kc::TriangulationOptions rounds;
          rounds.executor = kc::Executor::kRounds;
          auto tr = kc::Triangulation::Create(w.start, rounds);
          tri_rounds = std::make_unique<kc::Triangulation>(*std::move(tr));
        }
        if (engines.count("kinetri-device")) {
          kc::TriangulationOptions dev;
          dev.executor = kc::Executor::kDevice;
          dev.device_backend = kc::device::DeviceBackendAvailable(
                                   kc::device::DeviceBackend::kCuda)
                                   ? kc::device::DeviceBackend::kCuda
                                   : kc::device::DeviceBackend::kEmulated;
          auto td = kc::Triangulation::Create(w.start, dev);
          if (!td.ok()) {
            std::fprintf(stderr, "kinetri-device: %s\n",
                         td.status().ToString().c_str());
            return 1;
          }
          kc::device::LoopControl loop = td->device_executor()->loop_control();
          if (absl::GetFlag(FLAGS_device_loop_capacity) >= 0) {
            loop.capacity = static_cast<uint32_t>(
                absl::GetFlag(FLAGS_device_loop_capacity));
          }
          if (absl::GetFlag(FLAGS_device_loop_rounds) >= 0) {
            loop.rounds_per_check =
                static_cast<uint32_t>(absl::GetFlag(FLAGS_device_loop_rounds));
          }
          td->device_executor()->set_loop_control(loop);
          std::fprintf(stderr,
                       "[bench] kinetri-device runs on the %s backend (device "
                       "loops below %u edges, %u rounds per check)\n",
                       kc::device::DeviceBackendName(dev.device_backend),
                       loop.capacity, loop.rounds_per_check);
          tri_device = std::make_unique<kc::Triangulation>(*std::move(td));
        }
      }
      std::unique_ptr<CgalDt> moving;  // CGAL move(): handles by point id
      std::vector<CgalDt::Vertex_handle> handles;
      if (engines.count("cgal-move")) {
        moving = CgalBuild(w.start);
        handles.resize(n);
        for (auto v = moving->finite_vertices_begin();
             v != moving->finite_vertices_end(); ++v) {
          handles[v->info()] = v;
        }
      }
      std::vector<Vec2> pos = w.start;
      std::vector<uint32_t> all(n);
      for (uint32_t i = 0; i < n; ++i) all[i] = i;
      auto last_progress = Clock::now();
      // Each Kinetri engine's answers of the last step, in whose memory
      // the step's queries are built (RowOptions::recycle), as a simulation
      // loop that queries every step would: the peers write into buffers
      // allocated before their timers too.
      std::map<std::string, std::array<kc::NeighborLists, 7>> recycled;
      const bool recycle = absl::GetFlag(FLAGS_recycle_answers);
      for (int s = -1; s < steps; ++s) {  // step -1: warm-up
        if (std::chrono::duration<double>(Clock::now() - last_progress)
                .count() > 5.0) {
          std::fprintf(
              stderr, "[bench] %s %g n=%zu: step %d of %d (%.0f s)\n",
              wname.c_str(), param, n, s + 1, steps,
              std::chrono::duration<double>(Clock::now() - run_start).count());
          last_progress = Clock::now();
        }
        const auto d = w.motion(pos, s);
        for (size_t i = 0; i < n; ++i)
          pos[i] = {pos[i].x + d[i].x, pos[i].y + d[i].y};
        const bool measure = s >= 0;
        const bool check = s == 0;
        std::map<std::string, Answers> ans;
        auto rec = [&](const std::string& e, const std::string& ph, double ms) {
          if (!measure) return;
          times[e][ph].push_back(ms);
          spent[e] += ms;
        };
        // Kinetri (all threads; 1 thread for update + NN).
        for (auto* t :
             {tri.get(), tri1.get(), tri_rounds.get(), tri_device.get()}) {
          const std::string e = t == tri.get()          ? "kinetri"
                                : t == tri1.get()       ? "kinetri-1t"
                                : t == tri_rounds.get() ? "kinetri-rounds"
                                                        : "kinetri-device";
          if (t == nullptr || !on(e)) continue;
          // The batch is built outside the timer, as the peers get the
          // displacements without a copy.
          const kc::DisplacementBatch batch = kc::DisplacementBatch::Dense(d);
          auto t0 = Clock::now();
          auto rep = t->ApplyDisplacements(batch);
          rec(e, "update", Ms(t0));
          std::array<kc::NeighborLists, 7>& last = recycled[e];
          auto in = [&last, recycle](int i, kc::RowOptions o = {}) {
            if (recycle) o.recycle = &last[i];
            return o;
          };
          t0 = Clock::now();
          auto nn = kc::AllNearestNeighbors(*t, in(6));
          rec(e, "all_nn", Ms(t0));
          if (!rep.ok() || !nn.ok()) {
            std::fprintf(
                stderr, "%s %g n=%zu: %s failed: %s\n", wname.c_str(), param, n,
                e.c_str(),
                (!rep.ok() ? rep.status() : nn.status()).ToString().c_str());
            failed[e] = any_failed = true;
            continue;
          }
          Answers& a = ans[e];
          if (check) {
            for (uint32_t i = 0; i < n; ++i)
              a.nn_d2.push_back(D2(pos[i], pos[nn->ids[nn->offsets[i]]]));
          }
          last[6] = *std::move(nn);
          // The queries: on the CPU executor (all threads) and on the
          // device executor (its own query path, cross-checked too).
          if (t != tri.get() && t != tri_device.get()) continue;
          t0 = Clock::now();
          auto knn = kc::KNearestOfPoints(*t, all, 8, true, {}, in(0));
          rec(e, "knn8", Ms(t0));
          // Radius rows in the peers' output form: the set of neighbour
          // ids, unordered, no distances.
          kc::RowOptions set_only;
          set_only.closest_first = false;
          set_only.distances = false;
          set_only.plan = radius_plan;
          t0 = Clock::now();
          auto q8 = kc::WithinRadiusOfPoints(*t, all, r8, true, 0, {},
                                             in(1, set_only));
          rec(e, "radius8", Ms(t0));
          t0 = Clock::now();
          auto q32 = kc::WithinRadiusOfPoints(*t, all, r32, true, 0, {},
                                              in(2, set_only));
          rec(e, "radius32", Ms(t0));
          t0 = Clock::now();
          auto pnn = kc::KNearest(*t, qs, 1, {}, in(3));  // Nearest
          rec(e, "points_nn", Ms(t0));
          t0 = Clock::now();
          auto pknn = kc::KNearest(*t, qs, 8, {}, in(4));
          rec(e, "points_knn8", Ms(t0));
          t0 = Clock::now();
          auto pr8 = kc::WithinRadius(*t, qs, r8, 0, {}, in(5, set_only));
          rec(e, "points_radius8", Ms(t0));
          if (!knn.ok() || !q8.ok() || !q32.ok() || !pnn.ok() || !pknn.ok() ||
              !pr8.ok()) {
            std::fprintf(stderr, "%s %g n=%zu: %s: a query failed\n",
                         wname.c_str(), param, n, e.c_str());
            failed[e] = any_failed = true;
            continue;
          }
          if (check) {
            for (uint32_t i = 0; i < n; ++i) {
              for (uint64_t k = knn->offsets[i]; k < knn->offsets[i + 1]; ++k)
                a.knn_d2.push_back(D2(pos[i], pos[knn->ids[k]]));
              a.r8_count.push_back(q8->row_size(i));
              a.r32_count.push_back(q32->row_size(i));
            }
            for (size_t i = 0; i < qs.size(); ++i) {
              a.qnn_d2.push_back(D2(qs[i], pos[pnn->ids[pnn->offsets[i]]]));
              for (uint64_t k = pknn->offsets[i]; k < pknn->offsets[i + 1]; ++k)
                a.qknn_d2.push_back(D2(qs[i], pos[pknn->ids[k]]));
              a.qr8_count.push_back(pr8->row_size(i));
            }
          }
          last[0] = *std::move(knn);
          last[1] = *std::move(q8);
          last[2] = *std::move(q32);
          last[3] = *std::move(pnn);
          last[4] = *std::move(pknn);
          last[5] = *std::move(pr8);
        }
        if (on("cgal-rebuild")) {  // spatially sorted insertion
          const auto t0 = Clock::now();
          auto dt = CgalBuild(pos);
          rec("cgal-rebuild", "update", Ms(t0));
          if (check) ans["cgal-rebuild"].edges = CgalEdges(*dt);
        }
        if (on("cgal-move")) {  // CGAL's own kinetic path: move() each vertex
          const auto t0 = Clock::now();
          for (uint32_t i = 0; i < n; ++i) {
            handles[i] =
                moving->move(handles[i], K::Point_2(pos[i].x, pos[i].y));
          }
          rec("cgal-move", "update", Ms(t0));
          if (check) ans["cgal-move"].edges = CgalEdges(*moving);
        }
        if (on("grid")) {
          kinetri::bench::GridEngine grid;
          auto t0 = Clock::now();
          grid.Build(pos, std::sqrt((hi.x - lo.x) * (hi.y - lo.y) / n));
          rec("grid", "update", Ms(t0));
          t0 = Clock::now();
          auto nn = grid.AllNearest();
          rec("grid", "all_nn", Ms(t0));
          t0 = Clock::now();
          auto knn = grid.AllKNearest(8);
          rec("grid", "knn8", Ms(t0));
          t0 = Clock::now();
          auto pnn = grid.NearestOf(qs);
          rec("grid", "points_nn", Ms(t0));
          t0 = Clock::now();
          auto pknn = grid.KNearestOf(qs, 8);
          rec("grid", "points_knn8", Ms(t0));
          // Radius phases rebuild the grid with cell = r (its best case).
          std::vector<uint64_t> off8, off32, offq;
          std::vector<uint32_t> ids8, ids32, idsq;
          kinetri::bench::GridEngine gr;
          t0 = Clock::now();
          gr.Build(pos, r8);
          gr.AllWithinRadius(r8, &off8, &ids8);
          rec("grid", "radius8", Ms(t0));
          t0 = Clock::now();
          gr.Build(pos, r32);
          gr.AllWithinRadius(r32, &off32, &ids32);
          rec("grid", "radius32", Ms(t0));
          t0 = Clock::now();
          gr.Build(pos, r8);
          gr.WithinRadiusOf(qs, r8, &offq, &idsq);
          rec("grid", "points_radius8", Ms(t0));
          if (check) {
            Answers& a = ans["grid"];
            for (uint32_t i = 0; i < n; ++i) {
              a.nn_d2.push_back(D2(pos[i], pos[nn[i]]));
              for (int k = 0; k < 8; ++k)
                a.knn_d2.push_back(D2(pos[i], pos[knn[8 * i + k]]));
              a.r8_count.push_back(off8[i + 1] - off8[i]);
              a.r32_count.push_back(off32[i + 1] - off32[i]);
            }
            for (size_t i = 0; i < qs.size(); ++i) {
              a.qnn_d2.push_back(D2(qs[i], pos[pnn[i]]));
              for (int k = 0; k < 8; ++k)
                a.qknn_d2.push_back(D2(qs[i], pos[pknn[8 * i + k]]));
              a.qr8_count.push_back(offq[i + 1] - offq[i]);
            }
          }
        }
        if (on("grid-device")) {
          // The device backend kinetri-device runs on (CUDA when present).
          const auto backend = kc::device::DeviceBackendAvailable(
                                   kc::device::DeviceBackend::kCuda)
                                   ? kc::device::DeviceBackend::kCuda
                                   : kc::device::DeviceBackend::kEmulated;
          auto dgrid = kinetri::bench::MakeDeviceGrid(backend);
          if (dgrid == nullptr) {
            std::fprintf(stderr, "grid-device: no %s backend in this build\n",
                         kc::device::DeviceBackendName(backend));
            return 1;
          }
          auto t0 = Clock::now();
          dgrid->Build(pos, std::sqrt((hi.x - lo.x) * (hi.y - lo.y) / n));
          rec("grid-device", "update", Ms(t0));
          t0 = Clock::now();
          const std::vector<uint32_t> nn = dgrid->AllNearest();
          rec("grid-device", "all_nn", Ms(t0));
          if (check) {
            Answers& a = ans["grid-device"];
            for (uint32_t i = 0; i < n; ++i) {
              a.nn_d2.push_back(D2(pos[i], pos[nn[i]]));
            }
          }
        }
        if (on("nanoflann")) {
          NanoCloud cloud{&pos};
          auto t0 = Clock::now();
          NanoTree tree(2, cloud,
                        nanoflann::KDTreeSingleIndexAdaptorParams(10));
          rec("nanoflann", "update", Ms(t0));
          std::vector<uint32_t> nn(n), knn(8 * n), pnn(qs.size());
          t0 = Clock::now();
          kc::ParallelFor(
              0, n,
              [&](size_t i) {
                uint32_t idx[2];
                double d2[2];
                const double q[2] = {pos[i].x, pos[i].y};
                tree.knnSearch(q, 2, idx, d2);
                nn[i] = idx[0] == i ? idx[1] : idx[0];
              },
              256);
          rec("nanoflann", "all_nn", Ms(t0));
          t0 = Clock::now();
          kc::ParallelFor(
              0, n,
              [&](size_t i) {
                uint32_t idx[9];
                double d2[9];
                const double q[2] = {pos[i].x, pos[i].y};
                tree.knnSearch(q, 9, idx, d2);
                int k = 0;
                for (int j = 0; j < 9 && k < 8; ++j) {
                  if (idx[j] != i) knn[8 * i + k++] = idx[j];
                }
              },
              256);
          rec("nanoflann", "knn8", Ms(t0));
          // Radius searches count their matches (results unsorted, reused
          // per-thread buffers: nanoflann's fastest mode).
          auto radius = [&](const std::vector<Vec2>& from, double rr, bool self,
                            std::vector<uint64_t>* cnt) {
            cnt->assign(from.size(), 0);
            nanoflann::SearchParams params;
            params.sorted = false;
            kc::ParallelFor(
                0, from.size(),
                [&](size_t i) {
                  thread_local std::vector<std::pair<uint32_t, double>> m;
                  const double q[2] = {from[i].x, from[i].y};
                  (*cnt)[i] =
                      tree.radiusSearch(q, rr * rr, m, params) - (self ? 1 : 0);
                },
                256);
          };
          std::vector<uint64_t> c8, c32, cq;
          t0 = Clock::now();
          radius(pos, r8, true, &c8);
          rec("nanoflann", "radius8", Ms(t0));
          t0 = Clock::now();
          radius(pos, r32, true, &c32);
          rec("nanoflann", "radius32", Ms(t0));
          t0 = Clock::now();
          kc::ParallelFor(
              0, qs.size(),
              [&](size_t i) {
                uint32_t idx;
                double d2;
                const double q[2] = {qs[i].x, qs[i].y};
                tree.knnSearch(q, 1, &idx, &d2);
                pnn[i] = idx;
              },
              256);
          rec("nanoflann", "points_nn", Ms(t0));
          std::vector<uint32_t> pknn(8 * qs.size());
          t0 = Clock::now();
          kc::ParallelFor(
              0, qs.size(),
              [&](size_t i) {
                double d2[8];
                const double q[2] = {qs[i].x, qs[i].y};
                tree.knnSearch(q, 8, &pknn[8 * i], d2);
              },
              256);
          rec("nanoflann", "points_knn8", Ms(t0));
          t0 = Clock::now();
          radius(qs, r8, false, &cq);
          rec("nanoflann", "points_radius8", Ms(t0));
          if (check) {
            Answers& a = ans["nanoflann"];
            for (uint32_t i = 0; i < n; ++i) {
              a.nn_d2.push_back(D2(pos[i], pos[nn[i]]));
              for (int k = 0; k < 8; ++k)
                a.knn_d2.push_back(D2(pos[i], pos[knn[8 * i + k]]));
              a.r8_count.push_back(c8[i]);
              a.r32_count.push_back(c32[i]);
            }
            for (size_t i = 0; i < qs.size(); ++i) {
              a.qnn_d2.push_back(D2(qs[i], pos[pnn[i]]));
              for (int k = 0; k < 8; ++k)
                a.qknn_d2.push_back(D2(qs[i], pos[pknn[8 * i + k]]));
              a.qr8_count.push_back(cq[i]);
            }
          }
        }
        if (check && ans.count("kinetri")) {
          // Every engine must give the reference's answers; the edge sets of
          // the CGAL engines must equal Kinetri's Delaunay edges.
          const Answers& ref = ans["kinetri"];
          const auto kedges = tri->Edges();
          for (const auto& [e, a] : ans) {
            bool ok = true;
            auto same = [&](const auto& x, const auto& y) {
              ok &= x.empty() || y.empty() || x == y;
            };
            same(a.nn_d2, ref.nn_d2);
            same(a.knn_d2, ref.knn_d2);
            same(a.r8_count, ref.r8_count);
            same(a.r32_count, ref.r32_count);
            same(a.qnn_d2, ref.qnn_d2);
            same(a.qknn_d2, ref.qknn_d2);
            same(a.qr8_count, ref.qr8_count);
            if (e.rfind("cgal", 0) == 0) ok &= a.edges == kedges;
            if (!ok) {
              std::fprintf(stderr, "%s %g n=%zu: %s disagrees with kinetri\n",
                           wname.c_str(), param, n, e.c_str());
              failed[e] = true;
              any_failed = true;
            }
          }
        }
        for (const auto& [e, ms] : spent) {
          if (ms > budget_ms && !stopped[e] && s + 1 < steps) {
            stopped[e] = true;
            std::fprintf(stderr,
                         "[bench] %s %g n=%zu: %s stops after %d steps "
                         "(%.0f s, budget %.0f s)\n",
                         wname.c_str(), param, n, e.c_str(), s + 1, ms / 1000,
                         budget_ms / 1000);
          }
        }
      }
      for (const auto& [e, phases] : times) {
        for (const auto& [ph, v] : phases) {
          if (failed[e]) {
            std::printf("%-10s %6g %8zu %-13s %-14s %10s\n", wname.c_str(),
                        param, n, e.c_str(), ph.c_str(), "FAILED");
            continue;
          }
          Record r{wname,
                   param,
                   n,
                   e,
                   e == "kinetri-1t" || e.rfind("cgal", 0) == 0 ? 1 : threads,
                   ph,
                   Quantile(v, 0.5),
                   Quantile(v, 0.9),
                   static_cast<int>(v.size())};
          std::printf("%-10s %6g %8zu %-13s %-14s %10.3f %10.3f %5d\n",
                      wname.c_str(), param, n, e.c_str(), ph.c_str(),
                      r.median_ms, r.p90_ms, r.steps);
          records.push_back(r);
        }
      }
      std::fflush(stdout);
    }
  }
  if (!absl::GetFlag(FLAGS_json).empty()) {
    std::ofstream out(absl::GetFlag(FLAGS_json));
    out << "{\"machine\":" << MachineJson(commit) << ",\"records\":[\n";
    for (size_t i = 0; i < records.size(); ++i) {
      const Record& r = records[i];
      out << absl::StrCat("{\"workload\":\"", r.workload,
                          "\",\"param\":", r.param, ",\"n\":", r.n,
                          ",\"engine\":\"", r.engine,
                          "\",\"threads\":", r.threads, ",\"phase\":\"",
                          r.phase, "\",\"median_ms\":", r.median_ms,
                          ",\"p90_ms\":", r.p90_ms, ",\"steps\":", r.steps, "}")
          << (i + 1 < records.size() ? ",\n" : "\n");
    }
    out << "]}\n";
    std::printf("wrote %s\n", absl::GetFlag(FLAGS_json).c_str());
  }
  std::fprintf(stderr, "[bench] done in %.0f s\n",
               std::chrono::duration<double>(Clock::now() - run_start).count());
  return any_failed ? 1 : 0;
}
