// kinetri-cli: command-line access to kinetri-server (sessions, steps,
// queries, export).
#include <cstdio>
#include <fstream>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "absl/flags/flag.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"
#include "client/cpp/kinetri_client.h"
#include "core/program_flags.h"

ABSL_FLAG(std::string, server, "127.0.0.1:50051", "kinetri-server address");
ABSL_FLAG(std::string, session, "", "session name (sessions/{id})");
ABSL_FLAG(std::string, id, "", "create: session id to use (optional)");
ABSL_FLAG(std::string, csv, "",
          "create/move/query: CSV file of x,y rows (positions or deltas)");
ABSL_FLAG(uint32_t, random, 0, "create: use this many uniform random points");
ABSL_FLAG(double, sigma, 0.001, "move without --csv: Brownian step size");
ABSL_FLAG(int, steps, 1, "move: number of steps");
ABSL_FLAG(std::string, kind, "nearest", "query: nearest, knn or radius");
ABSL_FLAG(int, k, 4, "query knn: k");
ABSL_FLAG(double, r, 0.01, "query radius: r");
ABSL_FLAG(std::string, ids, "",
          "query: comma-separated point ids (default: all points, or the "
          "positions in --csv)");
ABSL_FLAG(std::string, out, "", "export: write positions and triangles here");

namespace {

const char kUsage[] =
    "kinetri-cli COMMAND [flags]\n"
    "commands:\n"
    "  create   --csv=points.csv | --random=N   [--id=name]\n"
    "  list\n"
    "  get      --session=sessions/ID\n"
    "  stats    --session=sessions/ID   (all session fields)\n"
    "  delete   --session=sessions/ID\n"
    "  move     --session=... (--csv=deltas.csv | --sigma=S) [--steps=N]\n"
    "  query    --session=... --kind=nearest|knn|radius [--k=K] [--r=R]\n"
    "           [--ids=1,2,3 | --csv=queries.csv]   (prints id,row,neighbour,"
    "distance)\n"
    "  export   --session=... --out=mesh.txt\n";

int Fail(const absl::Status& s) {
  std::fprintf(stderr, "kinetri-cli: %s\n", s.ToString().c_str());
  return 1;
}

absl::StatusOr<std::vector<double>> ReadCsv(const std::string& path) {
  std::ifstream in(path);
  if (!in) return absl::NotFoundError("cannot open " + path);
  std::vector<double> xy;
  std::string line;
  int lineno = 0;
  while (std::getline(in, line)) {
    ++lineno;
    if (line.empty() || line[0] == '#') continue;
    std::vector<std::string> f = absl::StrSplit(line, ',');
    double x, y;
    if (f.size() < 2 || !absl::SimpleAtod(f[0], &x) ||
        !absl::SimpleAtod(f[1], &y)) {
      if (lineno == 1) continue;  // header
      return absl::InvalidArgumentError(path + ":" + std::to_string(lineno) +
                                        ": expected x,y");
    }
    xy.push_back(x);
    xy.push_back(y);
  }
  return xy;
}

void Print(const kinetri::v1::Session& s) {
  std::printf("%s points=%llu sites=%llu step=%llu backend=%s\n",
              s.name().c_str(), (unsigned long long)s.point_count(),
              (unsigned long long)s.site_count(), (unsigned long long)s.step(),
              s.backend().c_str());
}

}  // namespace

int main(int argc, char** argv) {
  std::vector<char*> args = kinetri::ParseProgramFlags(argc, argv, kUsage);
  if (args.size() != 2) {
    std::fputs(kUsage, stderr);
    return 2;
  }
  const std::string cmd = args[1];
  kinetri::Client client(absl::GetFlag(FLAGS_server));
  const std::string session = absl::GetFlag(FLAGS_session);
  if (cmd == "create") {
    std::vector<double> xy;
    if (!absl::GetFlag(FLAGS_csv).empty()) {
      auto r = ReadCsv(absl::GetFlag(FLAGS_csv));
      if (!r.ok()) return Fail(r.status());
      xy = std::move(*r);
    } else {
      std::mt19937_64 rng(1);
      std::uniform_real_distribution<double> u(0, 1);
      xy.resize(2 * size_t{absl::GetFlag(FLAGS_random)});
      for (double& v : xy) v = u(rng);
    }
    auto s = client.CreateSession(xy, kinetri::v1::SessionOptions(),
                                  absl::GetFlag(FLAGS_id));
    if (!s.ok()) return Fail(s.status());
    Print(*s);
  } else if (cmd == "list") {
    auto l = client.ListSessions();
    if (!l.ok()) return Fail(l.status());
    for (const auto& s : *l) Print(s);
  } else if (cmd == "get" || cmd == "stats") {
    auto s = client.GetSession(session);
    if (!s.ok()) return Fail(s.status());
    if (cmd == "get") {
      Print(*s);
    } else {
      std::printf("%s", s->DebugString().c_str());
    }
  } else if (cmd == "delete") {
    const absl::Status st = client.DeleteSession(session);
    if (!st.ok()) return Fail(st);
  } else if (cmd == "move") {
    auto s = client.GetSession(session);
    if (!s.ok()) return Fail(s.status());
    auto stream = client.OpenSteps(session);
    if (!stream.ok()) return Fail(stream.status());
    std::vector<double> d;
    if (!absl::GetFlag(FLAGS_csv).empty()) {
      auto r = ReadCsv(absl::GetFlag(FLAGS_csv));
      if (!r.ok()) return Fail(r.status());
      d = std::move(*r);
    }
    std::mt19937_64 rng(2);
    std::normal_distribution<double> g(0, absl::GetFlag(FLAGS_sigma));
    for (int i = 0; i < absl::GetFlag(FLAGS_steps); ++i) {
      if (absl::GetFlag(FLAGS_csv).empty()) {
        d.assign(2 * s->point_count(), 0.0);
        for (double& v : d) v = g(rng);
      }
      auto ack = (*stream)->MoveBy(d);
      if (!ack.ok()) return Fail(ack.status());
      std::printf("step %llu: %s, %llu Delaunay flips, %.3f ms%s%s\n",
                  (unsigned long long)ack->step(), ack->stats().path().c_str(),
                  (unsigned long long)ack->stats().delaunay_flips(),
                  1e3 * ack->stats().update_seconds(),
                  ack->stats().fallback_reason().empty() ? "" : "; ",
                  ack->stats().fallback_reason().c_str());
    }
    const absl::Status st = (*stream)->Finish();
    if (!st.ok()) return Fail(st);
  } else if (cmd == "query") {
    kinetri::v1::QueryRequest req;
    req.set_session(session);
    req.set_include_distances(true);
    const std::string kind = absl::GetFlag(FLAGS_kind);
    if (kind == "nearest") {
      req.set_kind(kinetri::v1::QUERY_KIND_NEAREST);
    } else if (kind == "knn") {
      req.set_kind(kinetri::v1::QUERY_KIND_K_NEAREST);
      req.set_k(absl::GetFlag(FLAGS_k));
    } else if (kind == "radius") {
      req.set_kind(kinetri::v1::QUERY_KIND_RADIUS);
      req.set_radius(absl::GetFlag(FLAGS_r));
    } else {
      std::fprintf(stderr, "--kind must be nearest, knn or radius\n");
      return 2;
    }
    if (!absl::GetFlag(FLAGS_csv).empty()) {
      auto r = ReadCsv(absl::GetFlag(FLAGS_csv));
      if (!r.ok()) return Fail(r.status());
      req.mutable_positions()->mutable_xy()->Add(r->begin(), r->end());
    } else if (!absl::GetFlag(FLAGS_ids).empty()) {
      for (absl::string_view f :
           absl::StrSplit(absl::GetFlag(FLAGS_ids), ',')) {
        uint32_t id;
        if (!absl::SimpleAtoi(f, &id)) {
          std::fprintf(stderr, "--ids: bad id '%s'\n", std::string(f).c_str());
          return 2;
        }
        req.mutable_point_ids()->add_ids(id);
      }
      req.set_exclude_self(true);
    } else {
      req.mutable_all_points();
      req.set_exclude_self(true);
    }
    auto res = client.Query(req);
    if (!res.ok()) return Fail(res.status());
    std::printf("# step %llu\nrow,rank,neighbour,distance\n",
                (unsigned long long)res->step);
    for (size_t i = 0; i < res->rows(); ++i) {
      for (uint64_t j = res->offsets[i]; j < res->offsets[i + 1]; ++j) {
        std::printf("%zu,%llu,%u,%.17g\n", i,
                    (unsigned long long)(j - res->offsets[i]), res->ids[j],
                    res->distances.empty() ? 0.0 : res->distances[j]);
      }
    }
  } else if (cmd == "export") {
    auto mesh = client.Export(session);
    if (!mesh.ok()) return Fail(mesh.status());
    std::ofstream out(absl::GetFlag(FLAGS_out));
    if (!out) {
      std::fprintf(stderr, "--out: cannot write '%s'\n",
                   absl::GetFlag(FLAGS_out).c_str());
      return 1;
    }
    out.precision(17);
    out << "# step " << mesh->step << "\n# points x y\n";
    for (size_t i = 0; i + 1 < mesh->xy.size(); i += 2) {
      out << mesh->xy[i] << ' ' << mesh->xy[i + 1] << '\n';
    }
    out << "# triangles i j k\n";
    for (size_t t = 0; t + 2 < mesh->triangles.size(); t += 3) {
      out << mesh->triangles[t] << ' ' << mesh->triangles[t + 1] << ' '
          << mesh->triangles[t + 2] << '\n';
    }
    std::printf("wrote %zu points, %zu triangles to %s\n", mesh->xy.size() / 2,
                mesh->triangles.size() / 3, absl::GetFlag(FLAGS_out).c_str());
  } else {
    std::fputs(kUsage, stderr);
    return 2;
  }
  return 0;
}
