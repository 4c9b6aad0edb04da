// kinetri-sim: a simulation client that streams every step to kinetri-server
// (Brownian gas or diffusion-limited aggregation), queries neighbours each
// step, prints progress and draws the final triangulation.
#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <random>
#include <string>
#include <vector>

#include "absl/flags/flag.h"
#include "client/cpp/kinetri_client.h"
#include "client/cpp/security_flags.h"
#include "client/cpp/svg_writer.h"
#include "core/program_flags.h"

ABSL_FLAG(std::string, server, "127.0.0.1:50051", "kinetri-server address");
ABSL_FLAG(std::string, mode, "dla",
          "'dla': diffusion-limited aggregation (walkers stick to the "
          "cluster on contact, found by NN queries); 'brownian': every point "
          "diffuses, all-points NN and radius queries each step");
ABSL_FLAG(uint32_t, n, 20000, "number of particles");
ABSL_FLAG(int, steps, 100, "simulation steps");
ABSL_FLAG(double, sigma, 0.1,
          "step standard deviation in units of the mean spacing 1/sqrt(n)");
ABSL_FLAG(double, radius, 1.5, "radius query, in mean spacings (brownian)");
ABSL_FLAG(double, drift, 0.08,
          "dla: drift of walkers towards the centre per step, in mean "
          "spacings (keeps the demo short)");
ABSL_FLAG(double, stick, 0.8,
          "dla: a walker sticks when its nearest neighbour is in the "
          "aggregate and closer than this, in mean spacings");
ABSL_FLAG(std::string, svg, "kinetri.svg",
          "picture of the final triangulation ('' = none); a PNG is written "
          "beside it when rsvg-convert is installed");
ABSL_FLAG(bool, keep, false, "keep the session on the server at the end");
ABSL_FLAG(uint64_t, seed, 7, "random seed");

namespace {
using Clock = std::chrono::steady_clock;
double Since(Clock::time_point t) {
  return std::chrono::duration<double>(Clock::now() - t).count();
}
int Fail(const char* what, const absl::Status& s) {
  std::fprintf(stderr, "kinetri-sim: %s: %s\n", what, s.ToString().c_str());
  return 1;
}
}  // namespace

int main(int argc, char** argv) {
  kinetri::ParseProgramFlags(
      argc, argv,
      "Simulation client for kinetri-server: streams one displacement batch "
      "per step, queries nearest neighbours, prints steps/s and latencies, "
      "and writes an SVG of the final Delaunay triangulation.");
  const std::string mode = absl::GetFlag(FLAGS_mode);
  if (mode != "dla" && mode != "brownian") {
    std::fprintf(stderr, "--mode must be dla or brownian\n");
    return 2;
  }
  if (absl::GetFlag(FLAGS_n) < 3) {
    std::fprintf(stderr,
                 "kinetri-sim: --n=%u: a triangulation needs >= 3 "
                 "particles\n",
                 absl::GetFlag(FLAGS_n));
    return 2;
  }
  if (absl::GetFlag(FLAGS_steps) < 0) {
    std::fprintf(stderr, "kinetri-sim: --steps must be >= 0\n");
    return 2;
  }
  if (!(absl::GetFlag(FLAGS_sigma) >= 0.0 &&
        std::isfinite(absl::GetFlag(FLAGS_sigma)))) {
    std::fprintf(stderr, "kinetri-sim: --sigma must be a number >= 0\n");
    return 2;
  }
  // An unwritable picture is reported now, not after the whole run.
  const std::string svg_path = absl::GetFlag(FLAGS_svg);
  if (!svg_path.empty()) {
    const bool existed = std::ifstream(svg_path).good();
    std::ofstream probe(svg_path, std::ios::app);
    if (!probe) {
      std::fprintf(stderr, "kinetri-sim: --svg=%s: cannot write (%s)\n",
                   svg_path.c_str(), std::strerror(errno));
      return 2;
    }
    probe.close();
    if (!existed) std::remove(svg_path.c_str());
  }
  const uint32_t n = absl::GetFlag(FLAGS_n);
  const double spacing = 1.0 / std::sqrt(double(n));
  std::mt19937_64 rng(absl::GetFlag(FLAGS_seed));
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::vector<double> xy(2 * n);
  for (double& v : xy) v = u(rng);
  std::vector<bool> stuck(n, false);
  if (mode == "dla") {  // seed of the aggregate in the centre
    xy[0] = xy[1] = 0.5;
    stuck[0] = true;
  }

  kinetri::Client client(absl::GetFlag(FLAGS_server), 131072,
                         kinetri::SecurityFromFlags());
  auto t0 = Clock::now();
  auto session = client.CreateSession(xy, kinetri::v1::SessionOptions());
  if (!session.ok()) return Fail("create session", session.status());
  std::printf("kinetri-sim: %s, %u particles (%s) created in %.3f s\n",
              session->name().c_str(), n, mode.c_str(), Since(t0));
  auto steps = client.OpenSteps(session->name());
  if (!steps.ok()) return Fail("open step stream", steps.status());

  std::normal_distribution<double> g(0.0, absl::GetFlag(FLAGS_sigma) * spacing);
  const double stick = absl::GetFlag(FLAGS_stick) * spacing;
  const double drift = absl::GetFlag(FLAGS_drift) * spacing;
  const int total = absl::GetFlag(FLAGS_steps);
  double update_s = 0, query_s = 0;
  uint32_t n_stuck = mode == "dla" ? 1 : 0;
  const auto run_start = Clock::now();
  for (int s = 1; s <= total; ++s) {
    auto ts = Clock::now();
    absl::StatusOr<kinetri::v1::StepResponse> ack;
    std::vector<uint32_t> walkers;
    if (mode == "brownian") {
      std::vector<double> d(2 * n);
      for (double& v : d) v = g(rng);
      ack = (*steps)->MoveBy(d);
    } else {
      std::vector<double> d;
      for (uint32_t i = 0; i < n; ++i) {
        if (stuck[i]) continue;
        walkers.push_back(i);
        // Walkers drift slightly towards the centre so that the aggregate
        // grows within a short demo.
        const double dx = 0.5 - xy[2 * i], dy = 0.5 - xy[2 * i + 1];
        const double len = std::max(std::hypot(dx, dy), 1e-12);
        d.push_back(g(rng) + drift * dx / len);
        d.push_back(g(rng) + drift * dy / len);
      }
      if (walkers.empty()) break;
      ack = (*steps)->MoveBy(walkers, d);
      if (ack.ok()) {
        for (size_t k = 0; k < walkers.size(); ++k) {
          xy[2 * walkers[k]] += d[2 * k];
          xy[2 * walkers[k] + 1] += d[2 * k + 1];
        }
      }
    }
    if (!ack.ok()) return Fail("step", ack.status());
    update_s += Since(ts);

    ts = Clock::now();
    std::string extra;
    if (mode == "brownian") {
      auto nn = client.NearestOfAll(session->name());
      if (!nn.ok()) return Fail("nearest query", nn.status());
      std::vector<uint32_t> ids(n);
      for (uint32_t i = 0; i < n; ++i) ids[i] = i;
      auto near = client.WithinRadiusOfPoints(
          session->name(), ids, absl::GetFlag(FLAGS_radius) * spacing, true);
      if (!near.ok()) return Fail("radius query", near.status());
      extra = std::to_string(double(near->ids.size()) / n).substr(0, 4) +
              " neighbours within r per point";
    } else {
      auto nn = client.KNearestOfPoints(session->name(), walkers, 1, true);
      if (!nn.ok()) return Fail("nearest query", nn.status());
      for (size_t k = 0; k < walkers.size(); ++k) {
        if (nn->offsets[k + 1] == nn->offsets[k]) continue;
        const uint32_t j = nn->ids[nn->offsets[k]];
        if (stuck[j] && nn->distances[nn->offsets[k]] <= stick) {
          stuck[walkers[k]] = true;
          ++n_stuck;
        }
      }
      extra = std::to_string(n_stuck) + " particles in the aggregate";
    }
    query_s += Since(ts);
    if (s % std::max(1, total / 20) == 0 || s == total) {
      const auto& st = ack->stats();
      std::printf(
          "step %4d/%d  %6.1f steps/s  update %7.2f ms (%s, flips %llu)  "
          "query %7.2f ms  %s\n",
          s, total, s / Since(run_start), 1e3 * update_s / s, st.path().c_str(),
          (unsigned long long)st.delaunay_flips(), 1e3 * query_s / s,
          extra.c_str());
      std::fflush(stdout);
    }
  }
  const absl::Status fin = (*steps)->Finish();
  if (!fin.ok()) return Fail("finish step stream", fin);

  const std::string svg = absl::GetFlag(FLAGS_svg);
  if (!svg.empty()) {
    auto mesh = client.Export(session->name());
    if (!mesh.ok()) return Fail("export", mesh.status());
    auto nn = client.NearestOfAll(session->name());
    if (!nn.ok()) return Fail("nearest query", nn.status());
    std::vector<uint32_t> nearest(n, UINT32_MAX);
    for (uint32_t i = 0; i < n; ++i) {
      if (nn->offsets[i + 1] > nn->offsets[i])
        nearest[i] = nn->ids[nn->offsets[i]];
    }
    kinetri::SvgOptions opt;
    opt.title = mode == "dla" ? "Kinetri DLA (orange: aggregate)"
                              : "Kinetri Brownian gas";
    const absl::Status st =
        kinetri::WriteMeshSvg(*mesh, nearest, stuck, svg, opt);
    if (!st.ok()) return Fail("svg", st);
    std::printf("wrote %s\n", svg.c_str());
    if (std::system("command -v rsvg-convert >/dev/null 2>&1") == 0) {
      const std::string png = svg.substr(0, svg.rfind('.')) + ".png";
      const std::string cmd = "rsvg-convert -o '" + png + "' '" + svg + "'";
      if (std::system(cmd.c_str()) == 0) std::printf("wrote %s\n", png.c_str());
    }
  }
  if (!absl::GetFlag(FLAGS_keep)) {
    const absl::Status st = client.DeleteSession(session->name());
    if (!st.ok()) return Fail("delete session", st);
  }
  return 0;
}
