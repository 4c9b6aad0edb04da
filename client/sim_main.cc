// kinetri-sim: moves points by Brownian steps, keeps their Delaunay
// triangulation, answers proximity queries and draws the result.
#include <chrono>
#include <cmath>
#include <cstdio>
#include <random>
#include <string>
#include <vector>

#include "absl/flags/flag.h"
#include "absl/flags/parse.h"
#include "absl/flags/usage.h"
#include "client/svg_writer.h"
#include "core/queries.h"
#include "core/triangulation.h"

ABSL_FLAG(uint32_t, n, 20000, "number of points (uniform in the unit square)");
ABSL_FLAG(int, steps, 20, "number of Brownian steps");
ABSL_FLAG(double, sigma, 0.1,
          "step standard deviation in units of the mean spacing 1/sqrt(n)");
ABSL_FLAG(double, radius, 1.5,
          "fixed-radius query radius in units of the mean spacing");
ABSL_FLAG(int, threads, 0, "worker threads (0 = all cores)");
ABSL_FLAG(std::string, svg, "kinetri.svg",
          "where to write the picture of the final triangulation ('' = none)");
ABSL_FLAG(bool, validate, true,
          "check the triangulation exactly after every step (slower)");
ABSL_FLAG(uint64_t, seed, 7, "random seed");

namespace {
double Since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0)
      .count();
}
}  // namespace

int main(int argc, char** argv) {
  absl::SetProgramUsageMessage(
      "Moves points by Brownian steps and keeps their exact Delaunay "
      "triangulation with Kinetri's kinetic update; prints per-step figures "
      "(path taken, flips, time, query times) and writes an SVG picture.");
  absl::ParseCommandLine(argc, argv);
  namespace kc = kinetri::core;
  const uint32_t n = absl::GetFlag(FLAGS_n);
  const double spacing = 1.0 / std::sqrt(double(std::max<uint32_t>(n, 1)));
  std::mt19937_64 rng(absl::GetFlag(FLAGS_seed));
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::normal_distribution<double> g(0.0, absl::GetFlag(FLAGS_sigma) * spacing);
  std::vector<kc::Vec2> pts(n);
  for (auto& p : pts) p = {u(rng), u(rng)};

  kc::TriangulationOptions opt;
  opt.num_threads = absl::GetFlag(FLAGS_threads);
  auto t0 = std::chrono::steady_clock::now();
  auto tri = kc::Triangulation::Create(pts, opt);
  if (!tri.ok()) {
    std::fprintf(stderr, "create: %s\n", tri.status().ToString().c_str());
    return 1;
  }
  std::printf("kinetri-sim: %u points, %d threads, built in %.3f s\n", n,
              tri->num_threads(), Since(t0));
  const double r = absl::GetFlag(FLAGS_radius) * spacing;
  std::vector<uint32_t> all_ids(n);
  for (uint32_t i = 0; i < n; ++i) all_ids[i] = i;
  for (int s = 0; s < absl::GetFlag(FLAGS_steps); ++s) {
    std::vector<kc::Vec2> d(n);
    for (auto& v : d) v = {g(rng), g(rng)};
    auto rep = tri->ApplyDisplacements(kc::DisplacementBatch::Dense(d));
    if (!rep.ok()) {
      std::fprintf(stderr, "step %d: %s\n", s, rep.status().ToString().c_str());
      return 1;
    }
    t0 = std::chrono::steady_clock::now();
    auto nn = kc::AllNearestNeighbors(*tri);
    const double nn_s = Since(t0);
    t0 = std::chrono::steady_clock::now();
    auto fr = kc::WithinRadiusOfPoints(*tri, all_ids, r, true, 0);
    const double fr_s = Since(t0);
    if (!nn.ok() || !fr.ok()) return 1;
    std::string valid = "skipped";
    if (absl::GetFlag(FLAGS_validate)) {
      const absl::Status v = tri->Validate();
      valid = v.ok() ? "exact Delaunay: ok" : v.ToString();
      if (!v.ok()) {
        std::fprintf(stderr, "validation failed: %s\n", valid.c_str());
        return 1;
      }
    }
    std::printf(
        "step %3d/%d  update %7.2f ms  path %-10s substeps %u re-inserted %u  "
        "flips fix %llu hull %llu/%llu delaunay %llu  | all-NN %6.2f ms  "
        "FRNN(r=%.2g) %6.2f ms, %.1f per point | %s\n",
        s + 1, absl::GetFlag(FLAGS_steps), rep->seconds * 1e3,
        kc::UpdatePathName(rep->path), rep->substeps, rep->reinserted,
        (unsigned long long)rep->flips.interior_fix,
        (unsigned long long)rep->flips.hull_absorb,
        (unsigned long long)rep->flips.hull_release,
        (unsigned long long)rep->flips.delaunay, nn_s * 1e3, r, fr_s * 1e3,
        double(fr->ids.size()) / std::max<uint32_t>(n, 1), valid.c_str());
    std::fflush(stdout);
  }
  const std::string svg = absl::GetFlag(FLAGS_svg);
  if (!svg.empty() && n > 0) {
    auto nn = kc::AllNearestNeighbors(*tri);
    const absl::Status st =
        kinetri::client::WriteTriangulationSvg(*tri, *nn, svg);
    if (!st.ok()) {
      std::fprintf(stderr, "svg: %s\n", st.ToString().c_str());
      return 1;
    }
    std::printf("wrote %s\n", svg.c_str());
  }
  return 0;
}
