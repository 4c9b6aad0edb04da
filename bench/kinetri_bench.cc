// kinetri-bench: cost per simulation step of Kinetri and its peers (CGAL
// rebuild, a uniform grid, nanoflann), on moving points, in one process.
//
//   kinetri-bench --quick                 # N up to 100K, a few steps
//   kinetri-bench --json=out.json         # full matrix, JSON records
//
// For every workload and N, each engine runs the same steps; phases are timed
// separately (update/rebuild, all-points NN, all-points 8-NN, radius with a
// mean of 8 and 32 neighbours). On the first measured step all engines'
// answers are compared (by exact squared distances, so ties cannot differ);
// an engine that disagrees is reported as FAILED and not timed.
#include <CGAL/Delaunay_triangulation_2.h>
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <functional>
#include <map>
#include <memory>
#include <nanoflann.hpp>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "absl/flags/flag.h"
#include "absl/flags/parse.h"
#include "absl/flags/usage.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "bench/grid_engine.h"
#include "bench/nanoflann_cloud.h"
#include "core/parallel.h"
#include "core/queries.h"
#include "core/triangulation.h"

ABSL_FLAG(bool, quick, false, "reduced matrix: N = 10K, 100K; 5 steps");
ABSL_FLAG(std::string, json, "", "write the records to this JSON file");
ABSL_FLAG(std::string, sizes, "", "comma-separated N (overrides defaults)");
ABSL_FLAG(std::string, workloads, "brownian,shear,vortex,clustered",
          "comma-separated workloads");
ABSL_FLAG(int, steps, 0, "measured steps (0: 5 quick, 20 full)");

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
  if (name == "clustered") {
    // 90% of the points in 20 tight Gaussian clusters, 10% uniform: about
    // 1000x density contrast.
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
// distances of its k nearest others, and its radius counts.
struct Answers {
  std::vector<double> nn_d2, knn_d2;
  std::vector<uint64_t> r8_count, r32_count;
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

std::string MachineJson() {
  std::ifstream cpu("/proc/cpuinfo");
  std::string line, model = "unknown";
  while (std::getline(cpu, line)) {
    if (line.rfind("model name", 0) == 0) {
      model = line.substr(line.find(':') + 2);
      break;
    }
  }
  std::string commit = "unknown";
  if (FILE* f = popen("git rev-parse --short HEAD 2>/dev/null", "r")) {
    char buf[64] = {0};
    if (fgets(buf, sizeof buf, f))
      commit = std::string(buf, strcspn(buf, "\n"));
    pclose(f);
  }
  return absl::StrCat("{\"cpu\":\"", model,
                      "\",\"cores\":", std::thread::hardware_concurrency(),
                      ",\"gpu\":null,\"commit\":\"", commit, "\"}");
}

}  // namespace

int main(int argc, char** argv) {
  absl::SetProgramUsageMessage(
      "Benchmarks Kinetri against CGAL (rebuild), a uniform grid and "
      "nanoflann on moving points; per-phase median and p90 per step; "
      "answers cross-checked on the first step. --quick for a short run, "
      "--json=FILE for machine-readable records.");
  absl::ParseCommandLine(argc, argv);
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
                                                   : (quick ? 5 : 20);
  std::vector<std::pair<std::string, double>> loads;
  for (auto w : absl::StrSplit(absl::GetFlag(FLAGS_workloads), ',')) {
    const std::string name(w);
    if (name == "brownian") {
      for (double s : {0.01, 0.1, 1.0}) loads.push_back({name, s});
    } else if (name == "shear") {
      loads.push_back({name, 0.5});
    } else if (name == "vortex") {
      loads.push_back({name, 0.5});
    } else if (name == "clustered") {
      loads.push_back({name, 0.1});
    }
  }
  const int threads = static_cast<int>(std::thread::hardware_concurrency());
  std::vector<Record> records;
  std::printf("%-10s %6s %8s %-14s %-9s %10s %10s\n", "workload", "param", "n",
              "engine", "phase", "median_ms", "p90_ms");
  for (const auto& [wname, param] : loads) {
    for (size_t n : sizes) {
      Workload w = MakeWorkload(wname, param, n, 12345);
      // Radii giving a typical 8 and 32 neighbours on this point set: the
      // median distance to the 8th / 32nd neighbour over a sample (for
      // clustered sets the uniform-density formula would give thousands).
      double r8 = 0, r32 = 0;
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
        r8 = std::sqrt(Quantile(d8, 0.5));
        r32 = std::sqrt(Quantile(d32, 0.5));
      }
      // Engines keep their own copy of the positions and move it.
      std::map<std::string, std::map<std::string, std::vector<double>>> times;
      std::map<std::string, bool> failed;
      auto tri = kc::Triangulation::Create(w.start);
      kc::TriangulationOptions one;
      one.num_threads = 1;
      auto tri1 = kc::Triangulation::Create(w.start, one);
      std::vector<Vec2> pos = w.start;
      std::vector<uint32_t> all(n);
      for (uint32_t i = 0; i < n; ++i) all[i] = i;
      for (int s = -1; s < steps; ++s) {  // step -1: warm-up
        const auto d = w.motion(pos, s);
        for (size_t i = 0; i < n; ++i)
          pos[i] = {pos[i].x + d[i].x, pos[i].y + d[i].y};
        const bool measure = s >= 0;
        const bool check = s == 0;
        std::map<std::string, Answers> ans;
        auto rec = [&](const std::string& e, const std::string& ph, double ms) {
          if (measure) times[e][ph].push_back(ms);
        };
        // Kinetri (all threads, and 1 thread for update + NN).
        for (auto* t : {&tri, &tri1}) {
          const std::string e = t == &tri ? "kinetri" : "kinetri-1t";
          auto t0 = Clock::now();
          auto rep = (*t)->ApplyDisplacements(kc::DisplacementBatch::Dense(d));
          rec(e, "update", Ms(t0));
          if (!rep.ok()) failed[e] = true;
          t0 = Clock::now();
          auto nn = kc::AllNearestNeighbors(**t);
          rec(e, "all_nn", Ms(t0));
          if (t != &tri) continue;
          t0 = Clock::now();
          auto knn = kc::KNearestOfPoints(**t, all, 8, true);
          rec(e, "knn8", Ms(t0));
          t0 = Clock::now();
          auto q8 = kc::WithinRadiusOfPoints(**t, all, r8, true, 0);
          rec(e, "radius8", Ms(t0));
          t0 = Clock::now();
          auto q32 = kc::WithinRadiusOfPoints(**t, all, r32, true, 0);
          rec(e, "radius32", Ms(t0));
          if (check) {
            Answers& a = ans[e];
            for (uint32_t i = 0; i < n; ++i) {
              a.nn_d2.push_back(D2(pos[i], pos[nn->ids[nn->offsets[i]]]));
              for (uint64_t k = knn->offsets[i]; k < knn->offsets[i + 1]; ++k) {
                a.knn_d2.push_back(D2(pos[i], pos[knn->ids[k]]));
              }
              a.r8_count.push_back(q8->row_size(i));
              a.r32_count.push_back(q32->row_size(i));
            }
          }
        }
        {  // CGAL rebuild (spatially sorted insertion)
          using K = CGAL::Exact_predicates_inexact_constructions_kernel;
          std::vector<K::Point_2> p;
          p.reserve(n);
          for (const auto& v : pos) p.emplace_back(v.x, v.y);
          const auto t0 = Clock::now();
          CGAL::Delaunay_triangulation_2<K> dt(p.begin(), p.end());
          rec("cgal-rebuild", "update", Ms(t0));
          if (dt.number_of_vertices() == 0) failed["cgal-rebuild"] = true;
        }
        {  // grid
          kinetri::bench::GridEngine grid;
          auto t0 = Clock::now();
          grid.Build(pos, 1.0 / std::sqrt(double(n)));
          rec("grid", "update", Ms(t0));
          t0 = Clock::now();
          auto nn = grid.AllNearest();
          rec("grid", "all_nn", Ms(t0));
          t0 = Clock::now();
          auto knn = grid.AllKNearest(8);
          rec("grid", "knn8", Ms(t0));
          std::vector<uint64_t> off8, off32;
          std::vector<uint32_t> ids8, ids32;
          kinetri::bench::GridEngine g8;
          t0 = Clock::now();
          g8.Build(pos, r8);
          g8.AllWithinRadius(r8, &off8, &ids8);
          rec("grid", "radius8", Ms(t0));
          t0 = Clock::now();
          g8.Build(pos, r32);
          g8.AllWithinRadius(r32, &off32, &ids32);
          rec("grid", "radius32", Ms(t0));
          if (check) {
            Answers& a = ans["grid"];
            for (uint32_t i = 0; i < n; ++i) {
              a.nn_d2.push_back(D2(pos[i], pos[nn[i]]));
              for (int k = 0; k < 8; ++k)
                a.knn_d2.push_back(D2(pos[i], pos[knn[8 * i + k]]));
              a.r8_count.push_back(off8[i + 1] - off8[i]);
              a.r32_count.push_back(off32[i + 1] - off32[i]);
            }
          }
        }
        {  // nanoflann
          NanoCloud cloud{&pos};
          auto t0 = Clock::now();
          NanoTree tree(2, cloud,
                        nanoflann::KDTreeSingleIndexAdaptorParams(10));
          rec("nanoflann", "update", Ms(t0));
          std::vector<uint32_t> nn(n), knn(8 * n);
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
          std::vector<uint64_t> c8(n), c32(n);
          for (auto [rr, cnt, ph] : {std::make_tuple(r8, &c8, "radius8"),
                                     std::make_tuple(r32, &c32, "radius32")}) {
            t0 = Clock::now();
            kc::ParallelFor(
                0, n,
                [&](size_t i) {
                  std::vector<std::pair<uint32_t, double>> m;
                  const double q[2] = {pos[i].x, pos[i].y};
                  (*cnt)[i] = tree.radiusSearch(q, rr * rr, m,
                                                nanoflann::SearchParams()) -
                              1;
                },
                256);
            rec("nanoflann", ph, Ms(t0));
          }
          if (check) {
            Answers& a = ans["nanoflann"];
            for (uint32_t i = 0; i < n; ++i) {
              a.nn_d2.push_back(D2(pos[i], pos[nn[i]]));
              for (int k = 0; k < 8; ++k)
                a.knn_d2.push_back(D2(pos[i], pos[knn[8 * i + k]]));
              a.r8_count.push_back(c8[i]);
              a.r32_count.push_back(c32[i]);
            }
          }
        }
        if (check) {
          const Answers& ref = ans["kinetri"];
          for (const auto& [e, a] : ans) {
            if (a.nn_d2 != ref.nn_d2 || a.knn_d2 != ref.knn_d2 ||
                a.r8_count != ref.r8_count || a.r32_count != ref.r32_count) {
              std::fprintf(stderr, "%s %g n=%zu: %s disagrees with kinetri\n",
                           wname.c_str(), param, n, e.c_str());
              failed[e] = true;
            }
          }
        }
      }
      for (const auto& [e, phases] : times) {
        for (const auto& [ph, v] : phases) {
          if (failed[e]) {
            std::printf("%-10s %6g %8zu %-14s %-9s %10s\n", wname.c_str(),
                        param, n, e.c_str(), ph.c_str(), "FAILED");
            continue;
          }
          Record r{wname,
                   param,
                   n,
                   e,
                   e == "kinetri-1t" || e == "cgal-rebuild" ? 1 : threads,
                   ph,
                   Quantile(v, 0.5),
                   Quantile(v, 0.9),
                   static_cast<int>(v.size())};
          std::printf("%-10s %6g %8zu %-14s %-9s %10.3f %10.3f\n",
                      wname.c_str(), param, n, e.c_str(), ph.c_str(),
                      r.median_ms, r.p90_ms);
          records.push_back(r);
        }
      }
      std::fflush(stdout);
    }
  }
  if (!absl::GetFlag(FLAGS_json).empty()) {
    std::ofstream out(absl::GetFlag(FLAGS_json));
    out << "{\"machine\":" << MachineJson() << ",\"records\":[\n";
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
  return 0;
}
