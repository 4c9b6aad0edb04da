// kinetri-cli: command-line access to kinetri-server (sessions, steps,
// queries, export).
#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <iostream>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "absl/flags/flag.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"
#include "absl/time/time.h"
#include "client/cpp/kinetri_client.h"
#include "client/cpp/security_flags.h"
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
          "positions in --csv); remove: the points that leave; add: the "
          "client ids of the joining points (POINT_ID_POLICY_CLIENT "
          "sessions)");
ABSL_FLAG(std::string, out, "-",
          "export: file to write ('-': standard output)");
ABSL_FLAG(std::string, format, "text",
          "export: 'text' (# step, points x y, triangles i j k), 'obj' "
          "(Wavefront OBJ: v x y 0 / f i j k, 1-based) or 'csv' (point "
          "rows id,x,y then triangle rows t,i,j,k)");

namespace {

const char kUsage[] =
    "kinetri-cli COMMAND [flags]\n"
    "commands:\n"
    "  create   --csv=points.csv | --random=N   [--id=name]\n"
    "  list\n"
    "  get      --session=sessions/ID\n"
    "  stats    --session=sessions/ID   (every session field, one per line)\n"
    "  delete   --session=sessions/ID\n"
    "  move     --session=... (--csv=deltas.csv | --sigma=S) [--steps=N]\n"
    "  add      --session=... --csv=points.csv [--ids=7,8,9 (client ids)]\n"
    "           one step in which these points join\n"
    "  remove   --session=... --ids=1,2,3   one step in which they leave\n"
    "  query    --session=... --kind=nearest|knn|radius [--k=K] [--r=R]\n"
    "           [--ids=1,2,3 | --csv=queries.csv]\n"
    "           prints row,query_id,rank,neighbour,distance (row: position\n"
    "           in the request; query_id: the queried point's id, empty for\n"
    "           --csv positions; rank 0 = nearest)\n"
    "  export   --session=... [--out=FILE|-] [--format=text|obj|csv]\n"
    "Run kinetri-cli --help for the flags.\n";

// A usage error: says what was wrong, exit status 2.
int Usage(const std::string& what) {
  std::fprintf(stderr, "kinetri-cli: %s\n\n%s", what.c_str(), kUsage);
  return 2;
}

// An error from the server (or the connection): its gRPC code and message.
int Fail(const absl::Status& s) {
  std::fprintf(stderr, "kinetri-cli: %s\n", s.ToString().c_str());
  return 1;
}

// A local error (files): the message alone.
int FailLocal(const absl::Status& s) {
  std::fprintf(stderr, "kinetri-cli: %s\n", std::string(s.message()).c_str());
  return 1;
}

std::string FormatTime(const google::protobuf::Timestamp& t) {
  return absl::FormatTime(
      absl::RFC3339_full,
      absl::FromUnixSeconds(t.seconds()) + absl::Nanoseconds(t.nanos()),
      absl::UTCTimeZone());
}

absl::StatusOr<std::vector<double>> ReadCsv(const std::string& path) {
  std::ifstream in(path);
  if (!in) {
    return absl::NotFoundError(path + ": cannot open (" + std::strerror(errno) +
                               ")");
  }
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
  if (args.size() < 2) return Usage("no command given");
  if (args.size() > 2) {
    return Usage(std::string("unexpected argument '") + args[2] + "'");
  }
  const std::string cmd = args[1];
  static const char* kCommands[] = {"create", "list",  "get", "stats",
                                    "delete", "move",  "add", "remove",
                                    "query",  "export"};
  if (std::find(std::begin(kCommands), std::end(kCommands), cmd) ==
      std::end(kCommands)) {
    return Usage("unknown command '" + cmd + "'");
  }
  const std::string session = absl::GetFlag(FLAGS_session);
  const std::string csv = absl::GetFlag(FLAGS_csv);
  if (cmd != "create" && cmd != "list" && session.empty()) {
    return Usage(cmd + ": --session=sessions/ID is required");
  }
  kinetri::Client client(absl::GetFlag(FLAGS_server), 131072,
                         kinetri::SecurityFromFlags());
  if (cmd == "create") {
    const uint32_t random = absl::GetFlag(FLAGS_random);
    if (csv.empty() == (random == 0)) {
      return Usage(csv.empty()
                       ? "create: give the points: --csv=FILE or --random=N"
                       : "create: --csv and --random exclude each other");
    }
    std::vector<double> xy;
    if (!csv.empty()) {
      auto r = ReadCsv(csv);
      if (!r.ok()) return FailLocal(r.status());
      if (r->empty())
        return FailLocal(absl::InvalidArgumentError(csv + ": no x,y rows"));
      xy = std::move(*r);
    } else {
      std::mt19937_64 rng(1);
      std::uniform_real_distribution<double> u(0, 1);
      xy.resize(2 * size_t{random});
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
      std::printf(
          "name: %s\npoints: %llu\nsites: %llu\nstep: %llu\n"
          "backend: %s\nthreads: %u%s\npoint ids: %s\n"
          "created: %s\nupdated: %s\n",
          s->name().c_str(), (unsigned long long)s->point_count(),
          (unsigned long long)s->site_count(), (unsigned long long)s->step(),
          s->backend().c_str(), s->options().threads(),
          s->options().threads() == 0 ? " (the server's default)" : "",
          s->options().point_id_policy() == kinetri::v1::POINT_ID_POLICY_CLIENT
              ? "client"
              : "sequential",
          FormatTime(s->create_time()).c_str(),
          FormatTime(s->update_time()).c_str());
    }
  } else if (cmd == "delete") {
    const absl::Status st = client.DeleteSession(session);
    if (!st.ok()) return Fail(st);
  } else if (cmd == "move") {
    const int steps = absl::GetFlag(FLAGS_steps);
    const double sigma = absl::GetFlag(FLAGS_sigma);
    if (steps < 1) {
      return Usage("move: --steps=" + std::to_string(steps) + " must be >= 1");
    }
    if (csv.empty() && !(sigma > 0.0 && std::isfinite(sigma))) {
      return Usage("move: --sigma must be a positive number");
    }
    std::vector<double> d;
    if (!csv.empty()) {
      auto r = ReadCsv(csv);
      if (!r.ok()) return FailLocal(r.status());
      d = std::move(*r);
    }
    auto s = client.GetSession(session);
    if (!s.ok()) return Fail(s.status());
    auto stream = client.OpenSteps(session);
    if (!stream.ok()) return Fail(stream.status());
    std::mt19937_64 rng(2);
    std::normal_distribution<double> g(0, sigma);
    for (int i = 0; i < steps; ++i) {
      if (csv.empty()) {
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
  } else if (cmd == "add" || cmd == "remove") {
    if (cmd == "add" && csv.empty()) {
      return Usage("add: --csv=points.csv (x,y rows) is required");
    }
    if (cmd == "remove" && absl::GetFlag(FLAGS_ids).empty()) {
      return Usage("remove: --ids=1,2,3 is required");
    }
    std::vector<uint64_t> ids;
    if (!absl::GetFlag(FLAGS_ids).empty()) {
      for (absl::string_view f :
           absl::StrSplit(absl::GetFlag(FLAGS_ids), ',')) {
        uint64_t id;
        if (!absl::SimpleAtoi(f, &id)) {
          return Usage(cmd + ": --ids: bad id '" + std::string(f) + "'");
        }
        ids.push_back(id);
      }
    }
    auto s = client.GetSession(session);
    if (!s.ok()) return Fail(s.status());
    const bool client_ids =
        s->options().point_id_policy() == kinetri::v1::POINT_ID_POLICY_CLIENT;
    kinetri::PointChanges changes;
    if (cmd == "add") {
      auto r = ReadCsv(csv);
      if (!r.ok()) return FailLocal(r.status());
      changes.add_xy = std::move(*r);
      if (client_ids && 2 * ids.size() != changes.add_xy.size()) {
        return Usage(
            "add: this session names points by client id: --ids "
            "needs one id per row of --csv (" +
            std::to_string(changes.add_xy.size() / 2) + ")");
      }
      if (!client_ids && !ids.empty()) {
        return Usage("add: this session numbers points itself; no --ids");
      }
      changes.add_client_ids = ids;
    } else if (client_ids) {
      changes.remove_client_ids = ids;
    } else {
      for (uint64_t id : ids) {
        if (id > UINT32_MAX) {
          return Usage("remove: --ids: " + std::to_string(id) +
                       " is not a point id of this session");
        }
        changes.remove_ids.push_back(static_cast<uint32_t>(id));
      }
    }
    auto stream = client.OpenSteps(session);
    if (!stream.ok()) return Fail(stream.status());
    auto ack = (*stream)->Change(std::move(changes));
    if (!ack.ok()) return Fail(ack.status());
    const auto& st = ack->stats();
    std::printf("step %llu: %s, %u points %s, %llu points now",
                (unsigned long long)ack->step(), st.path().c_str(),
                cmd == "add" ? st.added_points() : st.removed_points(),
                cmd == "add" ? "joined" : "left",
                (unsigned long long)st.point_count());
    if (cmd == "add" && !client_ids && st.added_points() > 0) {
      std::printf(
          " (ids %llu..%llu)", (unsigned long long)st.first_added_id(),
          (unsigned long long)(st.first_added_id() + st.added_points() - 1));
    }
    if (cmd == "remove" && !client_ids) {
      std::printf(
          " (the others are numbered 0..%llu again, in order)",
          (unsigned long long)(st.point_count() ? st.point_count() - 1 : 0));
    }
    std::printf("\n");
    const absl::Status fin = (*stream)->Finish();
    if (!fin.ok()) return Fail(fin);
  } else if (cmd == "query") {
    kinetri::v1::QueryRequest req;
    req.set_session(session);
    req.set_include_distances(true);
    const std::string kind = absl::GetFlag(FLAGS_kind);
    if (kind == "nearest") {
      req.set_kind(kinetri::v1::QUERY_KIND_NEAREST);
    } else if (kind == "knn") {
      if (absl::GetFlag(FLAGS_k) < 1) return Usage("query: --k must be >= 1");
      req.set_kind(kinetri::v1::QUERY_KIND_K_NEAREST);
      req.set_k(absl::GetFlag(FLAGS_k));
    } else if (kind == "radius") {
      const double r = absl::GetFlag(FLAGS_r);
      if (!(r >= 0.0 && std::isfinite(r))) {
        return Usage("query: --r must be a number >= 0");
      }
      req.set_kind(kinetri::v1::QUERY_KIND_RADIUS);
      req.set_radius(r);
    } else {
      return Usage("query: --kind must be nearest, knn or radius");
    }
    if (!csv.empty() && !absl::GetFlag(FLAGS_ids).empty()) {
      return Usage("query: --csv and --ids exclude each other");
    }
    std::vector<uint64_t> query_ids;  // empty: positions from --csv
    if (!csv.empty()) {
      auto r = ReadCsv(csv);
      if (!r.ok()) return FailLocal(r.status());
      req.mutable_positions()->mutable_xy()->Add(r->begin(), r->end());
    } else if (!absl::GetFlag(FLAGS_ids).empty()) {
      for (absl::string_view f :
           absl::StrSplit(absl::GetFlag(FLAGS_ids), ',')) {
        uint64_t id;
        if (!absl::SimpleAtoi(f, &id)) {
          return Usage("query: --ids: bad id '" + std::string(f) + "'");
        }
        query_ids.push_back(id);
      }
      auto s = client.GetSession(session);
      if (!s.ok()) return Fail(s.status());
      const bool client_ids =
          s->options().point_id_policy() == kinetri::v1::POINT_ID_POLICY_CLIENT;
      for (uint64_t id : query_ids) {
        if (client_ids) {
          req.mutable_point_ids()->add_client_ids(id);
        } else {
          if (id > UINT32_MAX) {
            return Usage("query: --ids: " + std::to_string(id) +
                         " is not a point id of this session");
          }
          req.mutable_point_ids()->add_ids(static_cast<uint32_t>(id));
        }
      }
      req.set_exclude_self(true);
    } else {
      auto s = client.GetSession(session);
      if (!s.ok()) return Fail(s.status());
      if (s->options().point_id_policy() ==
          kinetri::v1::POINT_ID_POLICY_CLIENT) {
        auto mesh = client.Export(session);  // the client id of each row
        if (!mesh.ok()) return Fail(mesh.status());
        query_ids = mesh->point_ids;
      } else {
        for (uint64_t i = 0; i < s->point_count(); ++i) query_ids.push_back(i);
      }
      req.mutable_all_points();
      req.set_exclude_self(true);
    }
    auto res = client.Query(req);
    if (!res.ok()) return Fail(res.status());
    std::printf("# step %llu\nrow,query_id,rank,neighbour,distance\n",
                (unsigned long long)res->step);
    const bool cids = !res->client_ids.empty();
    for (size_t i = 0; i < res->rows(); ++i) {
      const std::string qid =
          query_ids.empty() ? "" : std::to_string(query_ids[i]);
      for (uint64_t j = res->offsets[i]; j < res->offsets[i + 1]; ++j) {
        std::printf(
            "%zu,%s,%llu,%llu,%.17g\n", i, qid.c_str(),
            (unsigned long long)(j - res->offsets[i]),
            (unsigned long long)(cids ? res->client_ids[j] : res->ids[j]),
            res->distances.empty() ? 0.0 : res->distances[j]);
      }
    }
  } else if (cmd == "export") {
    const std::string format = absl::GetFlag(FLAGS_format);
    if (format != "text" && format != "obj" && format != "csv") {
      return Usage("export: --format must be text, obj or csv");
    }
    const std::string path = absl::GetFlag(FLAGS_out);
    std::ofstream file;
    if (!path.empty() && path != "-") {
      file.open(path);
      if (!file) {
        return FailLocal(absl::PermissionDeniedError(
            path + ": cannot write (" + std::strerror(errno) + ")"));
      }
    }
    auto mesh = client.Export(session);
    if (!mesh.ok()) return Fail(mesh.status());
    std::ostream& out = file.is_open() ? file : std::cout;
    out.precision(17);
    const size_t np = mesh->xy.size() / 2, nt = mesh->triangles.size() / 3;
    auto point_id = [&](size_t i) -> uint64_t {
      return mesh->point_ids.empty() ? i : mesh->point_ids[i];
    };
    if (format == "text") {
      out << "# step " << mesh->step << "\n# points x y\n";
      for (size_t i = 0; i < np; ++i) {
        out << mesh->xy[2 * i] << ' ' << mesh->xy[2 * i + 1] << '\n';
      }
      out << "# triangles i j k\n";
      for (size_t t = 0; t < nt; ++t) {
        out << mesh->triangles[3 * t] << ' ' << mesh->triangles[3 * t + 1]
            << ' ' << mesh->triangles[3 * t + 2] << '\n';
      }
    } else if (format == "obj") {
      out << "# kinetri " << session << " step " << mesh->step << "\n";
      for (size_t i = 0; i < np; ++i) {
        out << "v " << mesh->xy[2 * i] << ' ' << mesh->xy[2 * i + 1] << " 0\n";
      }
      for (size_t t = 0; t < nt; ++t) {
        out << "f " << mesh->triangles[3 * t] + 1 << ' '
            << mesh->triangles[3 * t + 1] + 1 << ' '
            << mesh->triangles[3 * t + 2] + 1 << '\n';
      }
    } else {
      out << "kind,id,x,y\n";
      for (size_t i = 0; i < np; ++i) {
        out << "point," << point_id(i) << ',' << mesh->xy[2 * i] << ','
            << mesh->xy[2 * i + 1] << '\n';
      }
      out << "kind,i,j,k\n";
      for (size_t t = 0; t < nt; ++t) {
        out << "triangle," << point_id(mesh->triangles[3 * t]) << ','
            << point_id(mesh->triangles[3 * t + 1]) << ','
            << point_id(mesh->triangles[3 * t + 2]) << '\n';
      }
    }
    out.flush();
    if (!out) return FailLocal(absl::DataLossError(path + ": write failed"));
    if (file.is_open()) {
      std::fprintf(stderr, "wrote %zu points, %zu triangles to %s\n", np, nt,
                   path.c_str());
    }
  }
  return 0;
}
