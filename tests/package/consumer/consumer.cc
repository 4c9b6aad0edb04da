// Uses the installed core (a triangulation that moves, its nearest
// neighbours against brute force) and the installed C++ client (a call to a
// port nobody listens on fails cleanly). Exits 0 when all is as expected.
#include <algorithm>
#include <cstdio>
#include <random>
#include <utility>
#include <vector>

#include "client/cpp/kinetri_client.h"
#include "core/queries.h"
#include "core/triangulation.h"

int main() {
  using kinetri::core::Vec2;
  std::mt19937_64 rng(3);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::vector<Vec2> points(2000);
  for (Vec2& p : points) p = {u(rng), u(rng)};
  auto tri = kinetri::core::Triangulation::Create(points);
  if (!tri.ok()) {
    std::fprintf(stderr, "Create: %s\n", tri.status().ToString().c_str());
    return 1;
  }
  std::vector<Vec2> deltas(points.size());
  std::normal_distribution<double> d(0.0, 0.002);
  for (size_t i = 0; i < points.size(); ++i) {
    deltas[i] = {d(rng), d(rng)};
    points[i] = {points[i].x + deltas[i].x, points[i].y + deltas[i].y};
  }
  auto report = tri->ApplyDisplacements(
      kinetri::core::DisplacementBatch::Dense(std::move(deltas)));
  if (!report.ok() || !tri->Validate().ok()) {
    std::fprintf(stderr, "step failed\n");
    return 1;
  }
  auto nn = kinetri::core::AllNearestNeighbors(*tri);
  if (!nn.ok() || nn->num_queries() != points.size()) return 1;
  for (size_t i = 0; i < points.size(); ++i) {
    double best = 1e300;
    for (size_t j = 0; j < points.size(); ++j) {
      if (j == i) continue;
      const double dx = points[i].x - points[j].x;
      const double dy = points[i].y - points[j].y;
      best = std::min(best, dx * dx + dy * dy);
    }
    const uint32_t got = nn->ids[nn->offsets[i]];
    const double gx = points[i].x - points[got].x;
    const double gy = points[i].y - points[got].y;
    if (gx * gx + gy * gy != best) {
      std::fprintf(stderr, "nearest neighbour of %zu is wrong\n", i);
      return 1;
    }
  }
  kinetri::Client client("127.0.0.1:1");
  auto s = client.GetSession("sessions/none");
  if (s.ok() || s.status().code() != absl::StatusCode::kUnavailable) {
    std::fprintf(stderr, "client: %s\n", s.status().ToString().c_str());
    return 1;
  }
  std::printf("consumer: core and client from find_package(Kinetri) work\n");
  return 0;
}
