// Cost of durable sessions (--data_dir) on one session, in process: the
// step with and without the journal at each --fsync mode, the snapshot
// write, and the restore (snapshot read, CGAL build, journal replay).
//   kinetri-durability-bench --n=1000000 --steps=10 --dir=/tmp/kd
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <random>
#include <string>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/flags/flag.h"
#include "core/program_flags.h"
#include "core/triangulation.h"
#include "server/persistence.h"
#include "server/session_registry.h"

ABSL_FLAG(uint32_t, n, 1000000, "points in the session");
ABSL_FLAG(int, steps, 10, "measured steps per mode");
ABSL_FLAG(double, sigma, 0.1, "Brownian step in mean spacings");
ABSL_FLAG(std::string, dir, "/tmp/kinetri-durability-bench",
          "scratch data directory (emptied first and at the end)");

namespace {

using Clock = std::chrono::steady_clock;
namespace ks = kinetri::server;
namespace kc = kinetri::core;

double Ms(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

double Median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0.0 : v[v.size() / 2];
}

}  // namespace

int main(int argc, char** argv) {
  kinetri::ParseProgramFlags(
      argc, argv,
      "Measures durable sessions: step time without and with the journal "
      "(fsync always, everysec, no), snapshot write and restore time.");
  const uint32_t n = absl::GetFlag(FLAGS_n);
  const int steps = absl::GetFlag(FLAGS_steps);
  const std::string dir = absl::GetFlag(FLAGS_dir);
  std::mt19937_64 rng(1);
  std::uniform_real_distribution<double> u(0, 1);
  std::vector<kc::Vec2> pts(n);
  for (auto& p : pts) p = {u(rng), u(rng)};
  const double sigma = absl::GetFlag(FLAGS_sigma) / std::sqrt(double(n));
  std::normal_distribution<double> g(0, sigma);
  auto batch = [&] {
    std::vector<kc::Vec2> d(n);
    for (auto& v : d) v = {g(rng), g(rng)};
    return kc::DisplacementBatch::Dense(std::move(d));
  };
  std::printf("n=%u, %d steps per mode, Brownian %.3g spacings, dir %s\n", n,
              steps, absl::GetFlag(FLAGS_sigma), dir.c_str());
  std::printf("%-10s %12s %12s\n", "mode", "step_ms", "overhead_ms");
  double plain = 0.0;
  for (const std::string mode : {"memory", "no", "everysec", "always"}) {
    std::filesystem::remove_all(dir);
    auto tri = kc::Triangulation::Create(pts);
    if (!tri.ok()) return 1;
    ks::Session session("bench", std::move(*tri), "cpu", 0, 0);
    std::unique_ptr<ks::SessionStore> store;
    if (mode != "memory") {
      store = *ks::SessionStore::Open(dir, *ks::ParseFsyncPolicy(mode), 0);
      const auto t0 = Clock::now();
      auto journal = store->Create(session.Meta(0), *session.Read().tri);
      if (!journal.ok()) {
        std::fprintf(stderr, "%s\n", journal.status().ToString().c_str());
        return 1;
      }
      if (mode == "always") {
        std::printf(
            "%-10s %12.1f  (first snapshot, %.1f MB)\n", "snapshot", Ms(t0),
            std::filesystem::file_size(dir + "/sessions/@bench/snapshot") /
                1e6);
      }
      session.AttachJournal(*std::move(journal));
    }
    std::vector<double> times;
    for (int s = 0; s <= steps; ++s) {
      const kc::DisplacementBatch b = batch();
      const auto t0 = Clock::now();
      auto r = session.ApplyStep(s + 1, b, nullptr, nullptr);
      if (!r.ok()) {
        std::fprintf(stderr, "%s\n", r.status().ToString().c_str());
        return 1;
      }
      if (s > 0) times.push_back(Ms(t0));  // step 1 warms up
    }
    const double med = Median(times);
    if (mode == "memory") plain = med;
    std::printf("%-10s %12.1f %12.1f\n", mode.c_str(), med, med - plain);
    if (mode == "always") {
      // Restore: what a restart does (read, rebuild with CGAL, replay the
      // journal since the last snapshot).
      session.AttachJournal(nullptr);
      absl::flat_hash_map<std::string, std::string> broken;
      const auto t0 = Clock::now();
      auto loaded = store->LoadAll(&broken);
      const double read_ms = Ms(t0);
      if (loaded.size() != 1) return 1;
      auto t = kc::Triangulation::Create(loaded[0].positions);
      const double build_ms = Ms(t0) - read_ms;
      for (const auto& st : loaded[0].steps) {
        if (!t->ApplyDisplacements(st.batch).ok()) return 1;
      }
      std::printf(
          "restore    %12.1f  (read %.1f, CGAL build %.1f, %zu journaled "
          "steps replayed %.1f)\n",
          Ms(t0), read_ms, build_ms, loaded[0].steps.size(),
          Ms(t0) - read_ms - build_ms);
    }
  }
  std::filesystem::remove_all(dir);
  return 0;
}
