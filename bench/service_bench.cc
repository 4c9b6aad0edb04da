// kinetri-bench-service: the service on loopback against Redis GEO on the
// same workload, in one run.
//
// Starts kinetri-server and Debian's redis-server on free loopback ports,
// loads the same N points into both, then runs S steps: every point takes a
// Brownian step (sigma in mean spacings), the step is sent (Kinetri: one
// StreamSteps batch of deltas; Redis: GEOADD of every new position,
// pipelined), then a radius query around Q points (Kinetri: one Query;
// Redis: one GEOSEARCH BYRADIUS per point, pipelined). Reports steps/s and
// p50/p99 latency of update, query and the whole step, and the ratio.
// With --in_process (the default) the same steps and queries also run on a
// core::Triangulation in this process, between the server's and Redis's
// turns: the service's overhead over the library, per step and per query
// batch.
//
// Redis stores positions as 52-bit geohashes on a sphere: the unit square is
// mapped to a 1-degree lon/lat box at the equator and the radius to metres.
// Answers are cross-checked every --check_every steps: a point on which the
// two disagree must lie within --boundary_tolerance * r of the circle
// (geohash quantisation and the sphere), else the benchmark fails.
#include <fcntl.h>
#include <netinet/in.h>
#include <signal.h>
#include <spawn.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <memory>
#include <optional>
#include <random>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "absl/flags/flag.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "bench/resp_client.h"
#include "client/cpp/kinetri_client.h"
#include "core/program_flags.h"
#include "core/queries.h"
#include "core/triangulation.h"
#include "tests/e2e/server_process.h"

ABSL_FLAG(int, n, 100000, "points");
ABSL_FLAG(int, steps, 200, "measured steps (after one warm-up step)");
ABSL_FLAG(int, queries, 10000, "radius queries per step (around points)");
ABSL_FLAG(double, sigma, 0.1, "Brownian step, in mean spacings");
ABSL_FLAG(double, neighbours, 8.0, "mean neighbours per radius query");
ABSL_FLAG(int, check_every, 50, "cross-check answers every this many steps");
ABSL_FLAG(double, boundary_tolerance, 1e-2,
          "relative distance from the circle within which the two systems "
          "may disagree (geohash quantisation, spherical distances)");
ABSL_FLAG(std::string, server, "",
          "kinetri-server binary (default: ../server/kinetri-server next to "
          "this binary)");
ABSL_FLAG(std::string, redis, "/usr/bin/redis-server", "redis-server binary");
ABSL_FLAG(std::string, json, "", "write the results to this JSON file");
ABSL_FLAG(std::string, answer_encoding, "fixed",
          "how the server sends the query answers' offsets and ids: fixed "
          "(fixed-width fields, the C++ client's default) or varint");
ABSL_FLAG(bool, in_process, true,
          "also run the same steps and queries on a core::Triangulation in "
          "this process (same default options, all cores), after the "
          "server's and untimed for it: what the service adds to a step and "
          "a query batch; its rows must equal the server's");

namespace {

using Clock = std::chrono::steady_clock;
using kinetri::bench::RespClient;
using kinetri::bench::RespValue;

double Ms(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

double Quantile(std::vector<double> v, double q) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  return v[std::min(v.size() - 1,
                    static_cast<size_t>(q * (v.size() - 1) + 0.5))];
}

std::string SelfDir() {
  char buf[4096];
  const ssize_t k = readlink("/proc/self/exe", buf, sizeof buf - 1);
  if (k <= 0) return ".";
  std::string p(buf, static_cast<size_t>(k));
  return p.substr(0, p.rfind('/'));
}

int FreePort() {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  a.sin_port = 0;
  socklen_t len = sizeof a;
  if (bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0 ||
      getsockname(fd, reinterpret_cast<sockaddr*>(&a), &len) != 0) {
    close(fd);
    return -1;
  }
  const int port = ntohs(a.sin_port);
  close(fd);
  return port;
}

// redis-server as a child process on a loopback port, no persistence.
class RedisProcess {
 public:
  RedisProcess(const std::string& binary, int port) : port_(port) {
    const std::string p = std::to_string(port);
    std::vector<std::string> args = {
        binary, "--port",       p,    "--bind",      "127.0.0.1", "--save",
        "",     "--appendonly", "no", "--daemonize", "no"};
    std::vector<char*> argv;
    for (auto& a : args) argv.push_back(a.data());
    argv.push_back(nullptr);
    // Its log goes to /dev/null; errors show up as failed commands.
    posix_spawn_file_actions_t fa;
    posix_spawn_file_actions_init(&fa);
    posix_spawn_file_actions_addopen(&fa, STDOUT_FILENO, "/dev/null", O_WRONLY,
                                     0);
    if (posix_spawn(&pid_, binary.c_str(), &fa, nullptr, argv.data(),
                    environ) != 0) {
      pid_ = -1;
    }
    posix_spawn_file_actions_destroy(&fa);
  }
  ~RedisProcess() {
    if (pid_ > 0) {
      kill(pid_, SIGTERM);
      waitpid(pid_, nullptr, 0);
    }
  }
  bool started() const { return pid_ > 0; }
  int port() const { return port_; }

 private:
  pid_t pid_ = -1;
  int port_;
};

struct Series {
  std::vector<double> update, query, step;
};

void Report(const char* name, const Series& s, double seconds, int steps) {
  std::printf(
      "%-8s %8.1f steps/s | step p50 %8.2f p99 %8.2f ms | update p50 %8.2f "
      "p99 %8.2f | query p50 %8.2f p99 %8.2f\n",
      name, steps / seconds, Quantile(s.step, 0.5), Quantile(s.step, 0.99),
      Quantile(s.update, 0.5), Quantile(s.update, 0.99), Quantile(s.query, 0.5),
      Quantile(s.query, 0.99));
}

std::string SeriesJson(const char* name, const Series& s, double seconds,
                       int steps) {
  return absl::StrCat("{\"system\":\"", name,
                      "\",\"steps_per_s\":", steps / seconds,
                      ",\"step_p50_ms\":", Quantile(s.step, 0.5),
                      ",\"step_p99_ms\":", Quantile(s.step, 0.99),
                      ",\"update_p50_ms\":", Quantile(s.update, 0.5),
                      ",\"update_p99_ms\":", Quantile(s.update, 0.99),
                      ",\"query_p50_ms\":", Quantile(s.query, 0.5),
                      ",\"query_p99_ms\":", Quantile(s.query, 0.99), "}");
}

}  // namespace

int main(int argc, char** argv) {
  kinetri::ParseProgramFlags(
      argc, argv,
      "Service benchmark: kinetri-server vs redis-server (GEOADD + GEOSEARCH "
      "BYRADIUS) on loopback, same Brownian workload and radius queries, "
      "answers cross-checked. Example: kinetri-bench-service --n=100000 "
      "--steps=200 --queries=10000");
  const int n = absl::GetFlag(FLAGS_n);
  const int steps = absl::GetFlag(FLAGS_steps);
  const int nq = absl::GetFlag(FLAGS_queries);
  if (n < 2 || steps < 1 || nq < 1 || nq > n) {
    std::fprintf(stderr, "need n >= 2, steps >= 1, 1 <= queries <= n\n");
    return 2;
  }
  const std::string encoding_name = absl::GetFlag(FLAGS_answer_encoding);
  if (encoding_name != "fixed" && encoding_name != "varint") {
    std::fprintf(stderr, "--answer_encoding: fixed or varint, not \"%s\"\n",
                 encoding_name.c_str());
    return 2;
  }
  const kinetri::v1::AnswerEncoding encoding =
      encoding_name == "fixed" ? kinetri::v1::ANSWER_ENCODING_FIXED
                               : kinetri::v1::ANSWER_ENCODING_VARINT;
  const double spacing = 1.0 / std::sqrt(double(n));
  const double sigma = absl::GetFlag(FLAGS_sigma) * spacing;
  // Uniform density n per unit area: a disk of radius r holds n*pi*r^2.
  const double r =
      std::sqrt(absl::GetFlag(FLAGS_neighbours) / (M_PI * double(n)));
  // Unit square -> 1 degree box at the equator; Redis measures metres with
  // its Earth radius (6372797.560856 m).
  constexpr double kDeg = 1.0;
  constexpr double kEarth = 6372797.560856;
  const double metres_per_unit = kDeg * M_PI / 180.0 * kEarth;
  const std::string r_m = absl::StrCat(r * metres_per_unit);

  std::mt19937_64 rng(2026);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::vector<double> xy(2 * size_t(n));
  for (auto& c : xy) c = u(rng);

  // --- start both servers
  std::string server = absl::GetFlag(FLAGS_server);
  if (server.empty()) server = SelfDir() + "/../server/kinetri-server";
  if (access(server.c_str(), X_OK) != 0) {
    std::fprintf(stderr, "kinetri-server not found at %s (--server)\n",
                 server.c_str());
    return 2;
  }
  if (access(absl::GetFlag(FLAGS_redis).c_str(), X_OK) != 0) {
    std::fprintf(stderr,
                 "redis-server not found at %s (apt-get install redis-server, "
                 "or --redis)\n",
                 absl::GetFlag(FLAGS_redis).c_str());
    return 77;  // "skipped" for ctest
  }
  kinetri::testing::ServerProcess kserver(server);
  if (!kserver.ok()) {
    std::fprintf(stderr, "kinetri-server did not start\n");
    return 1;
  }
  RedisProcess redis(absl::GetFlag(FLAGS_redis), FreePort());
  RespClient rc;
  {
    absl::Status s = absl::UnavailableError("not started");
    for (int i = 0; i < 100 && redis.started(); ++i) {
      s = rc.Connect("127.0.0.1", redis.port());
      if (s.ok()) break;
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    if (!s.ok()) {
      std::fprintf(stderr, "redis-server did not start: %s\n",
                   s.ToString().c_str());
      return 1;
    }
  }
  std::fprintf(stderr,
               "[service] kinetri-server %s, redis-server 127.0.0.1:%d; n=%d "
               "steps=%d queries=%d sigma=%g spacings r=%g (%.1f m)\n",
               kserver.target().c_str(), redis.port(), n, steps, nq,
               absl::GetFlag(FLAGS_sigma), r, r * metres_per_unit);

  kinetri::Client kc(kserver.target());
  kinetri::v1::SessionOptions opts;
  auto session = kc.CreateSession(xy, opts);
  if (!session.ok()) {
    std::fprintf(stderr, "CreateSession: %s\n",
                 session.status().ToString().c_str());
    return 1;
  }
  auto stream = kc.OpenSteps(session->name());
  if (!stream.ok()) {
    std::fprintf(stderr, "OpenSteps: %s\n", stream.status().ToString().c_str());
    return 1;
  }
  std::vector<std::string> member(n);
  for (int i = 0; i < n; ++i) member[i] = std::to_string(i);
  auto geoadd_all = [&]() -> absl::Status {
    constexpr int kPerCommand = 1000;  // members per GEOADD
    std::vector<std::string> coords(2 * size_t(n));
    for (int i = 0; i < n; ++i) {
      coords[2 * i] = absl::StrCat(xy[2 * i] * kDeg);
      coords[2 * i + 1] = absl::StrCat(xy[2 * i + 1] * kDeg);
    }
    int commands = 0;
    for (int b = 0; b < n; b += kPerCommand) {
      std::vector<absl::string_view> args = {"GEOADD", "pts"};
      for (int i = b; i < std::min(n, b + kPerCommand); ++i) {
        args.push_back(coords[2 * i]);
        args.push_back(coords[2 * i + 1]);
        args.push_back(member[i]);
      }
      rc.Append(args);
      ++commands;
    }
    if (absl::Status s = rc.Flush(); !s.ok()) return s;
    for (int c = 0; c < commands; ++c) {
      auto v = rc.Read();
      if (!v.ok()) return v.status();
      if (v->type == RespValue::Type::kError)
        return absl::InternalError("GEOADD: " + v->str);
    }
    return absl::OkStatus();
  };
  if (absl::Status s = geoadd_all(); !s.ok()) {
    std::fprintf(stderr, "redis load: %s\n", s.ToString().c_str());
    return 1;
  }

  const bool in_process = absl::GetFlag(FLAGS_in_process);
  std::optional<kinetri::core::Triangulation> local;
  if (in_process) {
    std::vector<kinetri::core::Vec2> p(n);
    for (int i = 0; i < n; ++i) p[i] = {xy[2 * i], xy[2 * i + 1]};
    auto made = kinetri::core::Triangulation::Create(p);
    if (!made.ok()) {
      std::fprintf(stderr, "in-process: %s\n",
                   made.status().ToString().c_str());
      return 1;
    }
    local.emplace(std::move(*made));
  }
  Series ks, rs, ls;
  double k_total = 0, r_total = 0, l_total = 0;
  long local_mismatches = 0;
  int failures = 0;
  long boundary = 0, compared = 0;
  std::normal_distribution<double> g(0.0, sigma);
  std::vector<double> dxy(2 * size_t(n));
  std::vector<double> qxy(2 * size_t(nq));
  std::vector<int> qid(nq);
  for (int s = -1; s < steps; ++s) {
    for (int i = 0; i < 2 * n; ++i) {
      dxy[i] = g(rng);
      xy[i] += dxy[i];
    }
    for (int j = 0; j < nq; ++j) {
      qid[j] = static_cast<int>(u(rng) * n) % n;
      qxy[2 * j] = xy[2 * qid[j]];
      qxy[2 * j + 1] = xy[2 * qid[j] + 1];
    }
    // Kinetri: one step batch, then one radius query.
    auto t0 = Clock::now();
    auto ack = (*stream)->MoveBy(dxy);
    const double k_up = Ms(t0);
    auto t1 = Clock::now();
    // What Client::WithinRadius sends, in the chosen answer encoding.
    kinetri::v1::QueryRequest query;
    query.set_session(session->name());
    query.set_kind(kinetri::v1::QUERY_KIND_RADIUS);
    query.set_radius(r);
    query.set_include_distances(true);
    query.set_encoding(encoding);
    query.mutable_positions()->mutable_xy()->Add(qxy.begin(), qxy.end());
    auto kn = kc.Query(query);
    const double k_q = Ms(t1);
    if (!ack.ok() || !kn.ok()) {
      std::fprintf(stderr, "kinetri: %s\n",
                   (!ack.ok() ? ack.status() : kn.status()).ToString().c_str());
      return 1;
    }
    if (local) {
      // The library alone: the same step and query batch, with the options
      // the server passes for this request (the C++ client asks for
      // distances, so rows closest first with their distances).
      std::vector<kinetri::core::Vec2> d(n), qs(nq);
      for (int i = 0; i < n; ++i) d[i] = {dxy[2 * i], dxy[2 * i + 1]};
      for (int j = 0; j < nq; ++j) qs[j] = {qxy[2 * j], qxy[2 * j + 1]};
      t0 = Clock::now();
      auto rep = local->ApplyDisplacements(
          kinetri::core::DisplacementBatch::Dense(std::move(d)));
      const double l_up = Ms(t0);
      kinetri::core::RowOptions rows;
      rows.distances = true;
      rows.batch_queries = static_cast<uint64_t>(nq);
      t1 = Clock::now();
      auto ln = kinetri::core::WithinRadius(*local, qs, r, 0, {}, rows);
      const double l_q = Ms(t1);
      if (!rep.ok() || !ln.ok()) {
        std::fprintf(
            stderr, "in-process: %s\n",
            (!rep.ok() ? rep.status() : ln.status()).ToString().c_str());
        return 1;
      }
      for (int j = 0; j < nq; ++j) {
        std::vector<uint32_t> a(kn->ids.begin() + kn->offsets[j],
                                kn->ids.begin() + kn->offsets[j + 1]);
        std::vector<uint32_t> b(ln->ids.begin() + ln->offsets[j],
                                ln->ids.begin() + ln->offsets[j + 1]);
        std::sort(a.begin(), a.end());
        std::sort(b.begin(), b.end());
        if (a != b) ++local_mismatches;
      }
      if (s >= 0) {
        ls.update.push_back(l_up);
        ls.query.push_back(l_q);
        ls.step.push_back(l_up + l_q);
        l_total += l_up + l_q;
      }
    }
    // Redis: GEOADD every position (pipelined), GEOSEARCH per query point
    // (pipelined in chunks).
    t0 = Clock::now();
    if (absl::Status st = geoadd_all(); !st.ok()) {
      std::fprintf(stderr, "redis: %s\n", st.ToString().c_str());
      return 1;
    }
    const double r_up = Ms(t0);
    t1 = Clock::now();
    std::vector<std::vector<int>> rrows(nq);
    {
      constexpr int kChunk = 1000;
      std::vector<std::string> lon(nq), lat(nq);
      for (int j = 0; j < nq; ++j) {
        lon[j] = absl::StrCat(qxy[2 * j] * kDeg);
        lat[j] = absl::StrCat(qxy[2 * j + 1] * kDeg);
      }
      for (int b = 0; b < nq; b += kChunk) {
        const int e = std::min(nq, b + kChunk);
        for (int j = b; j < e; ++j) {
          rc.Append({"GEOSEARCH", "pts", "FROMLONLAT", lon[j], lat[j],
                     "BYRADIUS", r_m, "m"});
        }
        if (absl::Status st = rc.Flush(); !st.ok()) return 1;
        for (int j = b; j < e; ++j) {
          auto v = rc.Read();
          if (!v.ok() || v->type != RespValue::Type::kArray) {
            std::fprintf(
                stderr, "GEOSEARCH failed: %s\n",
                v.ok() ? v->str.c_str() : v.status().ToString().c_str());
            return 1;
          }
          for (const auto& m : v->elements) {
            int id = 0;
            if (absl::SimpleAtoi(m.str, &id)) rrows[j].push_back(id);
          }
        }
      }
    }
    const double r_q = Ms(t1);
    if (s >= 0) {
      ks.update.push_back(k_up);
      ks.query.push_back(k_q);
      ks.step.push_back(k_up + k_q);
      rs.update.push_back(r_up);
      rs.query.push_back(r_q);
      rs.step.push_back(r_up + r_q);
      k_total += k_up + k_q;
      r_total += r_up + r_q;
    }
    if (s >= 0 && s % absl::GetFlag(FLAGS_check_every) == 0) {
      // Cross-check: the sets may differ only next to the circle.
      const double tol = absl::GetFlag(FLAGS_boundary_tolerance);
      for (int j = 0; j < nq; ++j) {
        std::set<int> a(kn->ids.begin() + kn->offsets[j],
                        kn->ids.begin() + kn->offsets[j + 1]);
        std::set<int> b(rrows[j].begin(), rrows[j].end());
        compared += static_cast<long>(a.size());
        std::vector<int> diff;
        std::set_symmetric_difference(a.begin(), a.end(), b.begin(), b.end(),
                                      std::back_inserter(diff));
        for (int id : diff) {
          const double dx = xy[2 * id] - qxy[2 * j];
          const double dy = xy[2 * id + 1] - qxy[2 * j + 1];
          const double d = std::sqrt(dx * dx + dy * dy);
          if (std::abs(d - r) <= tol * r) {
            ++boundary;
          } else {
            ++failures;
          }
        }
      }
    }
    if (s >= 0 && (s + 1) % 20 == 0) {
      std::fprintf(stderr,
                   "[service] step %d/%d: kinetri %.1f ms, redis %.1f ms per "
                   "step so far\n",
                   s + 1, steps, k_total / (s + 1), r_total / (s + 1));
    }
  }
  (void)(*stream)->Finish();
  std::printf(
      "n=%d steps=%d queries/step=%d sigma=%g spacings, r=%g "
      "(mean %g neighbours), answers in %s encoding\n",
      n, steps, nq, absl::GetFlag(FLAGS_sigma), r,
      absl::GetFlag(FLAGS_neighbours), encoding_name.c_str());
  Report("kinetri", ks, k_total / 1000, steps);
  Report("redis", rs, r_total / 1000, steps);
  std::printf("throughput ratio kinetri/redis: %.2f\n", r_total / k_total);
  if (local) {
    Report("library", ls, l_total / 1000, steps);
    std::printf(
        "service / library (p50): query %.2f, update %.2f, step %.2f; rows "
        "differing from the server's: %ld\n",
        Quantile(ks.query, 0.5) / Quantile(ls.query, 0.5),
        Quantile(ks.update, 0.5) / Quantile(ls.update, 0.5),
        Quantile(ks.step, 0.5) / Quantile(ls.step, 0.5), local_mismatches);
  }
  std::printf(
      "cross-check: %ld neighbours compared, %ld boundary "
      "disagreements (within %g r of the circle), %d real\n",
      compared, boundary, absl::GetFlag(FLAGS_boundary_tolerance), failures);
  if (!absl::GetFlag(FLAGS_json).empty()) {
    std::ofstream out(absl::GetFlag(FLAGS_json));
    out << "{\"n\":" << n << ",\"steps\":" << steps << ",\"queries\":" << nq
        << ",\"sigma\":" << absl::GetFlag(FLAGS_sigma) << ",\"radius\":" << r
        << ",\"answer_encoding\":\"" << encoding_name << "\""
        << ",\"results\":[" << SeriesJson("kinetri", ks, k_total / 1000, steps)
        << "," << SeriesJson("redis", rs, r_total / 1000, steps)
        << (local ? "," + SeriesJson("library", ls, l_total / 1000, steps)
                  : std::string())
        << "],\"ratio\":" << r_total / k_total
        << ",\"boundary_disagreements\":" << boundary
        << ",\"mismatches\":" << failures
        << ",\"library_row_mismatches\":" << local_mismatches << "}\n";
  }
  return failures == 0 && local_mismatches == 0 ? 0 : 1;
}
