// End-to-end: the real kinetri-server driven by the C++ client over loopback.
#include <grpcpp/generic/generic_stub.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <condition_variable>
#include <csignal>
#include <mutex>
#include <random>
#include <set>
#include <string>
#include <thread>

#include "absl/strings/str_cat.h"
#include "client/cpp/kinetri_client.h"
#include "core/predicates.h"
#include "google/protobuf/descriptor.pb.h"
#include "grpc/reflection/v1/reflection.grpc.pb.h"
#include "tests/e2e/raw_call.h"
#include "tests/e2e/server_process.h"

namespace kinetri {
namespace {

using core::CompareCloser;
using core::CompareDistanceToRadius;
using core::Vec2;

// Built three times: for CPU sessions, with KINETRI_E2E_DEVICE for sessions
// on the device executor's emulated backend (server --device=emulated;
// sessions ask BACKEND_AUTO and get it), and with KINETRI_E2E_CUDA for
// sessions on the GPU (server --device=cuda; skipped without a GPU).
#if defined(KINETRI_E2E_CUDA)
constexpr char kBackend[] = "cuda";
#elif defined(KINETRI_E2E_DEVICE)
constexpr char kBackend[] = "emulated";
#else
constexpr char kBackend[] = "cpu";
#endif

Vec2 At(const std::vector<double>& xy, size_t i) {
  return {xy[2 * i], xy[2 * i + 1]};
}

// Ids ranked from q as the server documents (exact distance, then larger x,
// larger y, then smaller id).
std::vector<uint32_t> Rank(const std::vector<double>& xy, const Vec2& q,
                           int64_t self) {
  std::vector<uint32_t> ids;
  for (uint32_t i = 0; i < xy.size() / 2; ++i) {
    if (i != self) ids.push_back(i);
  }
  std::sort(ids.begin(), ids.end(), [&](uint32_t a, uint32_t b) {
    const int c = CompareCloser(q, At(xy, a), At(xy, b));
    return c != 0 ? c < 0 : a < b;
  });
  return ids;
}

std::vector<uint32_t> Row(const Neighbors& n, size_t i) {
  return {n.ids.begin() + n.offsets[i], n.ids.begin() + n.offsets[i + 1]};
}

class E2eTest : public ::testing::Test {
 protected:
  void SetUp() override {
    server_ = std::make_unique<testing::ServerProcess>(
        KINETRI_SERVER_BINARY,
        std::vector<std::string>{
            "--max_points=200000", "--max_sessions=4", "--threads=2",
            std::string("--device=") +
                (std::string(kBackend) == "cpu" ? "none" : kBackend)});
    ASSERT_TRUE(server_->ok());
    client_ = std::make_unique<Client>(server_->target(), /*chunk_points=*/700);
  }
  std::vector<double> Uniform(size_t n, uint64_t seed) {
    return testing::UniformXY(n, seed);
  }
  std::unique_ptr<testing::ServerProcess> server_;
  std::unique_ptr<Client> client_;
};

TEST_F(E2eTest, LifecycleStepsQueriesExport) {
  const size_t n = 5000;
  std::vector<double> xy = Uniform(n, 1);
  xy[2 * 7] = xy[2 * 8];  // a coincident pair
  xy[2 * 7 + 1] = xy[2 * 8 + 1];
  auto session = client_->CreateSession(xy, v1::SessionOptions(), "life");
  ASSERT_TRUE(session.ok()) << session.status();
  EXPECT_EQ(session->name(), "sessions/life");
  EXPECT_EQ(session->point_count(), n);
  EXPECT_EQ(session->site_count(), n - 1);
  EXPECT_EQ(session->backend(), kBackend);
  EXPECT_EQ(session->device_bytes(), 0u);  // nothing on a device yet

  auto stream = client_->OpenSteps(session->name());
  ASSERT_TRUE(stream.ok());
  std::mt19937_64 rng(2);
  std::normal_distribution<double> g(0, 0.1 / std::sqrt(double(n)));
  std::uniform_int_distribution<uint32_t> pick(0, n - 1);
  for (int s = 1; s <= 120; ++s) {
    absl::StatusOr<v1::StepResponse> ack;
    if (s % 10 == 0) {  // sparse
      std::vector<uint32_t> ids;
      std::vector<double> d;
      std::vector<bool> used(n, false);
      for (int k = 0; k < 50; ++k) {
        const uint32_t id = pick(rng);
        if (used[id]) continue;
        used[id] = true;
        ids.push_back(id);
        d.push_back(g(rng));
        d.push_back(g(rng));
      }
      ack = (*stream)->MoveBy(ids, d);
      for (size_t k = 0; k < ids.size(); ++k) {
        xy[2 * ids[k]] += d[2 * k];
        xy[2 * ids[k] + 1] += d[2 * k + 1];
      }
    } else if (s == 55) {  // absolute positions, dense
      std::vector<double> p = xy;
      for (double& v : p) v += g(rng);
      ack = (*stream)->MoveTo({}, p);
      xy = p;
    } else {
      std::vector<double> d(2 * n);
      for (double& v : d) v = g(rng);
      ack = (*stream)->MoveBy(d);
      for (size_t i = 0; i < d.size(); ++i) xy[i] += d[i];
    }
    ASSERT_TRUE(ack.ok()) << "step " << s << ": " << ack.status();
    ASSERT_EQ(ack->step(), uint64_t(s));
    ASSERT_FALSE(ack->stats().path().empty());
  }
  ASSERT_TRUE((*stream)->Finish().ok());
  {
    auto described = client_->GetSession(session->name());
    ASSERT_TRUE(described.ok());
    EXPECT_EQ(described->backend(), kBackend);
    if (std::string(kBackend) == "cpu") {
      EXPECT_EQ(described->device_bytes(), 0u);
      EXPECT_EQ(described->options().backend(), v1::BACKEND_CPU);
    } else {
      EXPECT_GT(described->device_bytes(), 0u);
      EXPECT_EQ(described->options().backend(), v1::BACKEND_CUDA);
    }
  }

  // Queries of every kind against brute force.
  auto all = client_->NearestOfAll(session->name());
  ASSERT_TRUE(all.ok()) << all.status();
  EXPECT_EQ(all->step, 120u);
  ASSERT_EQ(all->rows(), n);
  for (uint32_t i = 0; i < n; i += 7) {
    ASSERT_EQ(Row(*all, i), std::vector<uint32_t>{Rank(xy, At(xy, i), i)[0]});
  }
  std::vector<uint32_t> ids;
  for (uint32_t i = 0; i < n; i += 97) ids.push_back(i);
  auto knn = client_->KNearestOfPoints(session->name(), ids, 5, true);
  ASSERT_TRUE(knn.ok());
  for (size_t r = 0; r < ids.size(); ++r) {
    auto want = Rank(xy, At(xy, ids[r]), ids[r]);
    want.resize(5);
    ASSERT_EQ(Row(*knn, r), want);
  }
  const std::vector<double> q = Uniform(60, 3);
  auto knq = client_->KNearest(session->name(), q, 3);
  ASSERT_TRUE(knq.ok());
  const double radius = 0.03;
  auto rq = client_->WithinRadius(session->name(), q, radius);
  ASSERT_TRUE(rq.ok());
  for (size_t r = 0; r < q.size() / 2; ++r) {
    auto rank = Rank(xy, At(q, r), -1);
    std::vector<uint32_t> want3(rank.begin(), rank.begin() + 3);
    ASSERT_EQ(Row(*knq, r), want3);
    std::vector<uint32_t> in;
    for (uint32_t id : rank) {
      if (CompareDistanceToRadius(At(q, r), At(xy, id), radius) <= 0) {
        in.push_back(id);
      }
    }
    ASSERT_EQ(Row(*rq, r), in);
    ASSERT_EQ(rq->distances.size(), rq->ids.size());
  }
  auto capped =
      client_->WithinRadiusOfPoints(session->name(), ids, 0.05, true, 2);
  ASSERT_TRUE(capped.ok());
  EXPECT_FALSE(capped->truncated_rows.empty());
  for (size_t r = 0; r < ids.size(); ++r)
    EXPECT_LE(capped->offsets[r + 1] - capped->offsets[r], 2u);

  // Export: the positions the client tracked, and counter-clockwise
  // triangles covering every site.
  auto mesh = client_->Export(session->name());
  ASSERT_TRUE(mesh.ok());
  EXPECT_EQ(mesh->xy, xy);
  ASSERT_GT(mesh->triangles.size(), 3 * (n - 100));
  for (size_t t = 0; t < mesh->triangles.size(); t += 3) {
    ASSERT_GT(core::Orient2d(At(xy, mesh->triangles[t]),
                             At(xy, mesh->triangles[t + 1]),
                             At(xy, mesh->triangles[t + 2])),
              0);
  }
  auto listed = client_->ListSessions();
  ASSERT_TRUE(listed.ok());
  ASSERT_EQ(listed->size(), 1u);
  ASSERT_TRUE(client_->DeleteSession(session->name()).ok());
  EXPECT_EQ(client_->GetSession(session->name()).status().code(),
            absl::StatusCode::kNotFound);
}

TEST_F(E2eTest, ErrorsLeaveTheSessionUnchanged) {
  const size_t n = 500;
  const std::vector<double> xy = Uniform(n, 4);
  auto session = client_->CreateSession(xy, v1::SessionOptions(), "errs");
  ASSERT_TRUE(session.ok());
  const std::string name = session->name();
  auto expect_unchanged = [&] {
    auto s = client_->GetSession(name);
    ASSERT_TRUE(s.ok());
    EXPECT_EQ(s->step(), 0u);
    auto mesh = client_->Export(name);
    ASSERT_TRUE(mesh.ok());
    EXPECT_EQ(mesh->xy, xy);
  };
  {
    auto st = client_->OpenSteps(name);
    std::vector<double> d(2 * n, 0.001);
    d[2 * 13 + 1] = std::nan("");
    auto ack = (*st)->MoveBy(d);
    EXPECT_EQ(ack.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_NE(ack.status().message().find("deltas[13].y"), std::string::npos)
        << ack.status();
  }
  expect_unchanged();
  {
    auto st = client_->OpenSteps(name);
    auto ack = (*st)->MoveBy(std::vector<double>(2 * n - 2, 0.0));
    EXPECT_EQ(ack.status().code(), absl::StatusCode::kInvalidArgument);
  }
  {
    auto st = client_->OpenSteps(name);
    auto ack = (*st)->MoveBy({3, 5000}, {0.1, 0.1, 0.1, 0.1});
    EXPECT_EQ(ack.status().code(), absl::StatusCode::kNotFound);
  }
  expect_unchanged();
  {  // out-of-order step
    grpc::ClientContext ctx;
    auto stream = client_->stub()->StreamSteps(&ctx);
    v1::StepRequest req;
    req.set_session(name);
    req.set_step(5);
    for (size_t i = 0; i < 2 * n; ++i) req.add_xy(0.0);
    req.set_end_of_step(true);
    stream->Write(req);
    stream->WritesDone();
    v1::StepResponse resp;
    EXPECT_FALSE(stream->Read(&resp));
    EXPECT_EQ(stream->Finish().error_code(),
              grpc::StatusCode::FAILED_PRECONDITION);
  }
  {  // disconnect in the middle of a chunked step
    grpc::ClientContext ctx;
    auto stream = client_->stub()->StreamSteps(&ctx);
    v1::StepRequest req;
    req.set_session(name);
    req.set_step(1);
    for (size_t i = 0; i < n; ++i) req.add_xy(0.01);
    stream->Write(req);  // no end_of_step
    ctx.TryCancel();
    stream->Finish();
  }
  expect_unchanged();
  EXPECT_EQ(client_->GetSession("sessions/nope").status().code(),
            absl::StatusCode::kNotFound);
  EXPECT_EQ(client_->GetSession("bad/name").status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(client_->KNearestOfPoints(name, {1}, 0, true).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(client_->WithinRadius(name, {0.5, 0.5}, -1.0).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(client_->KNearest(name, {0.5, std::nan("")}, 2).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(client_->KNearestOfPoints(name, {9999}, 1, true).status().code(),
            absl::StatusCode::kNotFound);
  // Limits.
  EXPECT_EQ(client_->CreateSession(Uniform(200001, 5), v1::SessionOptions())
                .status()
                .code(),
            absl::StatusCode::kResourceExhausted);
  EXPECT_EQ(
      client_->CreateSession(xy, v1::SessionOptions(), "errs").status().code(),
      absl::StatusCode::kAlreadyExists);
  for (int i = 0; i < 3; ++i) {
    ASSERT_TRUE(
        client_->CreateSession(Uniform(50, 10 + i), v1::SessionOptions()).ok());
  }
  EXPECT_EQ(client_->CreateSession(xy, v1::SessionOptions()).status().code(),
            absl::StatusCode::kResourceExhausted);
  expect_unchanged();
}

TEST_F(E2eTest, ConcurrentSessionsStayIndependent) {
  const size_t n = 3000;
  std::vector<std::vector<double>> xy = {Uniform(n, 21), Uniform(n, 22)};
  std::vector<std::string> names;
  for (int k = 0; k < 2; ++k) {
    auto s = client_->CreateSession(xy[k], v1::SessionOptions());
    ASSERT_TRUE(s.ok());
    names.push_back(s->name());
  }
  auto worker = [&](int k) {
    Client own(server_->target());
    auto st = own.OpenSteps(names[k]);
    if (!st.ok()) return;
    std::mt19937_64 rng(30 + k);
    std::normal_distribution<double> g(0, 0.002);
    for (int s = 0; s < 60; ++s) {
      std::vector<double> d(2 * n);
      for (double& v : d) v = g(rng);
      if (!(*st)->MoveBy(d).ok()) return;
      for (size_t i = 0; i < d.size(); ++i) xy[k][i] += d[i];
      if (!own.NearestOfAll(names[k]).ok()) return;
    }
    (*st)->Finish().ok();
  };
  std::thread a(worker, 0), b(worker, 1);
  a.join();
  b.join();
  for (int k = 0; k < 2; ++k) {
    auto mesh = client_->Export(names[k]);
    ASSERT_TRUE(mesh.ok());
    EXPECT_EQ(mesh->step, 60u);
    EXPECT_EQ(mesh->xy, xy[k]);
  }
}

TEST_F(E2eTest, ClientIdPolicy) {
  const size_t n = 2000;
  std::vector<double> xy = Uniform(n, 50);
  std::vector<uint64_t> cid(n);
  for (size_t i = 0; i < n; ++i) cid[i] = 1'000'000'007ull * (i + 3) + 11;
  auto s = client_->CreateSessionWithIds(xy, cid, v1::SessionOptions(), "cids");
  ASSERT_TRUE(s.ok()) << s.status();
  EXPECT_EQ(s->options().point_id_policy(), v1::POINT_ID_POLICY_CLIENT);
  // Move ten points named by client id.
  auto st = client_->OpenSteps(s->name());
  std::vector<uint64_t> moved;
  std::vector<double> d;
  for (size_t i = 0; i < 10; ++i) {
    moved.push_back(cid[i * 37]);
    d.push_back(0.001 * (i + 1));
    d.push_back(-0.0005 * i);
    xy[2 * i * 37] += d[2 * i];
    xy[2 * i * 37 + 1] += d[2 * i + 1];
  }
  ASSERT_TRUE((*st)->MoveByClientIds(moved, d).ok());
  // Unknown client id and sequential ids are refused; nothing changes.
  auto bad = (*st)->MoveByClientIds({42}, {0.1, 0.1});
  EXPECT_EQ(bad.status().code(), absl::StatusCode::kNotFound);
  EXPECT_NE(bad.status().message().find("client_ids[0] = 42"),
            std::string::npos);
  auto st2 = client_->OpenSteps(s->name());
  EXPECT_EQ((*st2)->MoveBy({1}, {0.1, 0.1}).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(client_->GetSession(s->name())->step(), 1u);
  // k-NN of points named by client id; answers in client ids.
  v1::QueryRequest q;
  q.set_session(s->name());
  q.set_kind(v1::QUERY_KIND_K_NEAREST);
  q.set_k(3);
  q.set_exclude_self(true);
  for (size_t i = 0; i < n; i += 101)
    q.mutable_point_ids()->add_client_ids(cid[i]);
  auto res = client_->Query(q);
  ASSERT_TRUE(res.ok()) << res.status();
  EXPECT_TRUE(res->ids.empty());
  size_t row = 0;
  for (size_t i = 0; i < n; i += 101, ++row) {
    auto want = Rank(xy, At(xy, i), i);
    std::vector<uint64_t> want_c;
    for (int k = 0; k < 3; ++k) want_c.push_back(cid[want[k]]);
    std::vector<uint64_t> got(res->client_ids.begin() + res->offsets[row],
                              res->client_ids.begin() + res->offsets[row + 1]);
    ASSERT_EQ(got, want_c) << "row " << row;
  }
  auto mesh = client_->Export(s->name());
  ASSERT_TRUE(mesh.ok());
  EXPECT_EQ(mesh->point_ids, cid);
  EXPECT_EQ(mesh->xy, xy);
  // Duplicate client ids are refused at creation.
  std::vector<uint64_t> dup = {5, 6, 5};
  EXPECT_EQ(
      client_
          ->CreateSessionWithIds({0, 0, 1, 0, 0, 1}, dup, v1::SessionOptions())
          .status()
          .code(),
      absl::StatusCode::kInvalidArgument);
}

// Points join and leave with steps, on both id policies: after every step
// the export equals a model of the documented numbering, the triangles are
// CGAL's (by the core tests; here: the mesh is exported whole), and k-NN
// answers equal brute force on the model.
TEST_F(E2eTest, PointsJoinAndLeave) {
  for (const bool with_client_ids : {false, true}) {
    SCOPED_TRACE(with_client_ids ? "client ids" : "sequential ids");
    std::mt19937_64 rng(with_client_ids ? 61 : 60);
    std::vector<double> xy = Uniform(1500, with_client_ids ? 61 : 60);
    std::vector<uint64_t> cid;
    for (size_t i = 0; i < xy.size() / 2; ++i)
      cid.push_back(3 * i + (1ull << 40));
    uint64_t next_cid = 1ull << 50;
    auto s = with_client_ids
                 ? client_->CreateSessionWithIds(xy, cid, v1::SessionOptions())
                 : client_->CreateSession(xy, v1::SessionOptions());
    ASSERT_TRUE(s.ok()) << s.status();
    auto stream = client_->OpenSteps(s->name());
    ASSERT_TRUE(stream.ok());
    std::uniform_real_distribution<double> u(-0.1, 1.1);
    for (int step = 1; step <= 6; ++step) {
      SCOPED_TRACE(absl::StrCat("step ", step));
      const size_t n = xy.size() / 2;
      // Some points move (sparse), others leave, new ones join: inside,
      // outside the hull, and on existing points.
      std::vector<uint8_t> gone(n, 0);
      PointChanges ch;
      for (int k = 0; k < 60; ++k) {
        const uint32_t id = rng() % n;
        if (gone[id]) continue;
        gone[id] = 1;
        if (with_client_ids) {
          ch.remove_client_ids.push_back(cid[id]);
        } else {
          ch.remove_ids.push_back(id);
        }
      }
      std::vector<double> add;
      for (int k = 0; k < 80; ++k) {
        if (k % 10 == 0) {
          const size_t j = rng() % n;
          add.push_back(xy[2 * j]);
          add.push_back(xy[2 * j + 1]);
        } else {
          add.push_back(u(rng));
          add.push_back(u(rng));
        }
        if (with_client_ids) ch.add_client_ids.push_back(next_cid++);
      }
      // A removed client id joins again at a new place.
      if (with_client_ids && !ch.remove_client_ids.empty()) {
        ch.add_client_ids.back() = ch.remove_client_ids.front();
      }
      ch.add_xy = add;
      std::vector<uint32_t> moved;
      std::vector<uint64_t> moved_cid;
      std::vector<double> d;
      for (uint32_t i = 0; i < n; i += 13) {
        if (gone[i]) continue;
        moved.push_back(i);
        moved_cid.push_back(cid[i]);
        d.push_back(1e-4 * (i % 7));
        d.push_back(-1e-4 * (i % 5));
      }
      (*stream)->SetNextChanges(ch);
      auto ack = with_client_ids ? (*stream)->MoveByClientIds(moved_cid, d)
                                 : (*stream)->MoveBy(moved, d);
      ASSERT_TRUE(ack.ok()) << ack.status();
      // The model.
      for (size_t k = 0; k < moved.size(); ++k) {
        xy[2 * moved[k]] += d[2 * k];
        xy[2 * moved[k] + 1] += d[2 * k + 1];
      }
      std::vector<double> nxy;
      std::vector<uint64_t> ncid;
      for (size_t i = 0; i < n; ++i) {
        if (gone[i]) continue;
        nxy.push_back(xy[2 * i]);
        nxy.push_back(xy[2 * i + 1]);
        ncid.push_back(cid[i]);
      }
      const size_t survivors = nxy.size() / 2;
      nxy.insert(nxy.end(), add.begin(), add.end());
      ncid.insert(ncid.end(), ch.add_client_ids.begin(),
                  ch.add_client_ids.end());
      xy = nxy;
      cid = ncid;
      EXPECT_EQ(ack->stats().removed_points(),
                ch.remove_ids.size() + ch.remove_client_ids.size());
      EXPECT_EQ(ack->stats().added_points(), add.size() / 2);
      EXPECT_EQ(ack->stats().point_count(), xy.size() / 2);
      if (!with_client_ids) {
        EXPECT_EQ(ack->stats().first_added_id(), survivors);
      }
      EXPECT_EQ(client_->GetSession(s->name())->point_count(), xy.size() / 2);
      auto mesh = client_->Export(s->name());
      ASSERT_TRUE(mesh.ok()) << mesh.status();
      ASSERT_EQ(mesh->xy, xy);
      if (with_client_ids) {
        ASSERT_EQ(mesh->point_ids, cid);
      }
      // k-NN of every 37th point against brute force.
      v1::QueryRequest q;
      q.set_session(s->name());
      q.set_kind(v1::QUERY_KIND_K_NEAREST);
      q.set_k(4);
      q.set_exclude_self(true);
      std::vector<size_t> targets;
      for (size_t i = 0; i < xy.size() / 2; i += 37) {
        targets.push_back(i);
        if (with_client_ids) {
          q.mutable_point_ids()->add_client_ids(cid[i]);
        } else {
          q.mutable_point_ids()->add_ids(static_cast<uint32_t>(i));
        }
      }
      auto res = client_->Query(q);
      ASSERT_TRUE(res.ok()) << res.status();
      for (size_t row = 0; row < targets.size(); ++row) {
        auto want = Rank(xy, At(xy, targets[row]), targets[row]);
        want.resize(4);
        if (with_client_ids) {
          std::vector<uint64_t> want_c, got;
          for (uint32_t w : want) want_c.push_back(cid[w]);
          got.assign(res->client_ids.begin() + res->offsets[row],
                     res->client_ids.begin() + res->offsets[row + 1]);
          ASSERT_EQ(got, want_c) << "row " << row;
        } else {
          ASSERT_EQ(Row(*res, row), want) << "row " << row;
        }
      }
    }
    // A step of changes only; then refusals that change nothing.
    PointChanges only;
    only.add_xy = {0.5, 0.5};
    if (with_client_ids) only.add_client_ids = {7};
    auto ack = (*stream)->Change(only);
    ASSERT_TRUE(ack.ok()) << ack.status();
    EXPECT_EQ(ack->stats().moved_points(), 0u);
    const uint64_t count = xy.size() / 2 + 1;
    EXPECT_EQ(ack->stats().point_count(), count);
    PointChanges bad;
    if (with_client_ids) {
      bad.remove_client_ids = {123456789};
    } else {
      bad.remove_ids = {static_cast<uint32_t>(count)};
    }
    EXPECT_EQ((*stream)->Change(bad).status().code(),
              absl::StatusCode::kNotFound);
    stream = client_->OpenSteps(s->name());
    bad = {};
    bad.add_xy = {0.25, 0.25};
    if (with_client_ids) {
      bad.add_client_ids = {7};  // exists already
      EXPECT_EQ((*stream)->Change(bad).status().code(),
                absl::StatusCode::kAlreadyExists);
    } else {
      bad.add_client_ids = {7};  // sequential sessions name no points
      EXPECT_EQ((*stream)->Change(bad).status().code(),
                absl::StatusCode::kInvalidArgument);
    }
    stream = client_->OpenSteps(s->name());
    bad = {};
    bad.add_xy = {0.25, std::nan("")};
    if (with_client_ids) bad.add_client_ids = {8};
    EXPECT_EQ((*stream)->Change(bad).status().code(),
              absl::StatusCode::kInvalidArgument);
    auto now = client_->GetSession(s->name());
    EXPECT_EQ(now->point_count(), count);
    EXPECT_EQ(now->step(), 7u);
    // Growth stops at the server's --max_points (200000).
    stream = client_->OpenSteps(s->name());
    bad = {};
    bad.add_xy.assign(2 * 200000, 0.5);
    if (with_client_ids) {
      for (uint64_t i = 0; i < 200000; ++i)
        bad.add_client_ids.push_back(i + 100);
    }
    EXPECT_EQ((*stream)->Change(bad).status().code(),
              absl::StatusCode::kResourceExhausted);
    EXPECT_EQ(client_->GetSession(s->name())->point_count(), count);
    ASSERT_TRUE(client_->DeleteSession(s->name()).ok());
  }
}

// The lists of a step may come in any chunk order: a chunk of leaving
// points before the (sparse) moves.
TEST_F(E2eTest, StepChunksInAnyOrder) {
  std::vector<double> xy = Uniform(50, 81);
  auto s = client_->CreateSession(xy, v1::SessionOptions());
  ASSERT_TRUE(s.ok()) << s.status();
  grpc::ClientContext ctx;
  client_->Prepare(&ctx, s->name());
  auto stream = client_->stub()->StreamSteps(&ctx);
  v1::StepRequest a, b;
  a.set_session(s->name());
  a.set_step(1);
  a.add_remove_ids(5);
  b.set_step(1);
  b.add_ids(3);
  b.add_xy(0.001);
  b.add_xy(0.0);
  b.add_add_xy(0.5);
  b.add_add_xy(0.25);
  b.set_end_of_step(true);
  ASSERT_TRUE(stream->Write(a));
  ASSERT_TRUE(stream->Write(b));
  v1::StepResponse resp;
  ASSERT_TRUE(stream->Read(&resp));
  EXPECT_EQ(resp.stats().removed_points(), 1u);
  EXPECT_EQ(resp.stats().added_points(), 1u);
  EXPECT_EQ(resp.stats().moved_points(), 1u);
  EXPECT_EQ(resp.stats().point_count(), 50u);
  stream->WritesDone();
  EXPECT_TRUE(stream->Finish().ok());
  auto mesh = client_->Export(s->name());
  ASSERT_TRUE(mesh.ok());
  xy[6] += 0.001;
  xy.erase(xy.begin() + 10, xy.begin() + 12);
  xy.push_back(0.5);
  xy.push_back(0.25);
  EXPECT_EQ(mesh->xy, xy);
}

// Server reflection v1 (and v1alpha, the same messages) describe the API:
// services, the file of a symbol with its imports, errors for unknown names.
TEST_F(E2eTest, ReflectionV1AndV1alpha) {
  namespace refl = grpc::reflection::v1;
  auto channel = grpc::CreateChannel(server_->target(),
                                     grpc::InsecureChannelCredentials());
  auto stub = refl::ServerReflection::NewStub(channel);
  grpc::ClientContext ctx;
  auto stream = stub->ServerReflectionInfo(&ctx);
  refl::ServerReflectionRequest req;
  refl::ServerReflectionResponse resp;
  req.set_list_services("");
  ASSERT_TRUE(stream->Write(req));
  ASSERT_TRUE(stream->Read(&resp));
  std::set<std::string> services;
  for (const auto& s : resp.list_services_response().service()) {
    services.insert(s.name());
  }
  EXPECT_TRUE(services.count("kinetri.v1.KinetriService"));
  EXPECT_TRUE(services.count("grpc.reflection.v1.ServerReflection"));
  req.set_file_containing_symbol("kinetri.v1.KinetriService");
  ASSERT_TRUE(stream->Write(req));
  ASSERT_TRUE(stream->Read(&resp));
  std::set<std::string> files;
  bool has_steps = false;
  for (const std::string& bytes :
       resp.file_descriptor_response().file_descriptor_proto()) {
    google::protobuf::FileDescriptorProto f;
    ASSERT_TRUE(f.ParseFromString(bytes));
    files.insert(f.name());
    for (const auto& svc : f.service()) {
      for (const auto& m : svc.method()) {
        has_steps |=
            svc.name() == "KinetriService" && m.name() == "StreamSteps";
      }
    }
  }
  EXPECT_TRUE(has_steps);
  EXPECT_TRUE(files.count("kinetri/v1/kinetri.proto"));
  EXPECT_TRUE(files.count("google/protobuf/timestamp.proto"));
  // A message type resolves to its file (already sent on this stream).
  req.set_file_containing_symbol("kinetri.v1.StepRequest");
  ASSERT_TRUE(stream->Write(req));
  ASSERT_TRUE(stream->Read(&resp));
  EXPECT_FALSE(resp.has_error_response());
  EXPECT_EQ(resp.original_request().file_containing_symbol(),
            "kinetri.v1.StepRequest");
  req.set_file_containing_symbol("kinetri.v1.NoSuchThing");
  ASSERT_TRUE(stream->Write(req));
  ASSERT_TRUE(stream->Read(&resp));
  EXPECT_EQ(resp.error_response().error_code(), grpc::StatusCode::NOT_FOUND);
  req.set_file_by_filename("no/such.proto");
  ASSERT_TRUE(stream->Write(req));
  ASSERT_TRUE(stream->Read(&resp));
  EXPECT_EQ(resp.error_response().error_code(), grpc::StatusCode::NOT_FOUND);
  stream->WritesDone();
  EXPECT_TRUE(stream->Finish().ok());

  // v1alpha answers the same request (same wire format).
  grpc::GenericStub generic(channel);
  grpc::ClientContext actx;
  grpc::CompletionQueue cq;
  req.set_list_services("");
  std::string bytes = req.SerializeAsString();
  grpc::ByteBuffer out_buf;
  {
    grpc::Slice slice(bytes);
    out_buf = grpc::ByteBuffer(&slice, 1);
  }
  auto call = generic.PrepareCall(
      &actx, "/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo",
      &cq);
  void* tag = nullptr;
  bool ok = false;
  call->StartCall(reinterpret_cast<void*>(1));
  ASSERT_TRUE(cq.Next(&tag, &ok) && ok);
  call->WriteLast(out_buf, grpc::WriteOptions(), reinterpret_cast<void*>(2));
  ASSERT_TRUE(cq.Next(&tag, &ok) && ok);
  grpc::ByteBuffer in_buf;
  call->Read(&in_buf, reinterpret_cast<void*>(3));
  ASSERT_TRUE(cq.Next(&tag, &ok) && ok);
  std::vector<grpc::Slice> slices;
  ASSERT_TRUE(in_buf.Dump(&slices).ok());
  std::string in_bytes;
  for (const auto& sl : slices) {
    in_bytes.append(reinterpret_cast<const char*>(sl.begin()), sl.size());
  }
  refl::ServerReflectionResponse alpha;
  ASSERT_TRUE(alpha.ParseFromString(in_bytes));
  bool alpha_has = false;
  for (const auto& svc : alpha.list_services_response().service()) {
    alpha_has |= svc.name() == "kinetri.v1.KinetriService";
  }
  EXPECT_TRUE(alpha_has);
  grpc::Status st;
  call->Finish(&st, reinterpret_cast<void*>(4));
  ASSERT_TRUE(cq.Next(&tag, &ok));
  EXPECT_TRUE(st.ok()) << st.error_message();
  cq.Shutdown();
  while (cq.Next(&tag, &ok)) {
  }
}

// Query targets beyond one message stream (StreamQuery): the client (700
// points per message) cuts 5000 positions and 3000 ids into messages; the
// answers equal brute force. Wrong streams are refused.
TEST_F(E2eTest, QueryTargetsStream) {
  const std::vector<double> xy = Uniform(4000, 71);
  auto s = client_->CreateSession(xy, v1::SessionOptions());
  ASSERT_TRUE(s.ok()) << s.status();
  const std::vector<double> qs = Uniform(5000, 72);
  auto r = client_->KNearest(s->name(), qs, 3);
  ASSERT_TRUE(r.ok()) << r.status();
  ASSERT_EQ(r->offsets.size(), 5001u);
  for (size_t i = 0; i < 5000; i += 7) {
    auto want = Rank(xy, At(qs, i), -1);
    want.resize(3);
    ASSERT_EQ(Row(*r, i), want) << "query " << i;
  }
  std::vector<uint32_t> ids;
  for (uint32_t i = 0; i < 3000; ++i) ids.push_back((i * 7) % 4000);
  auto rp = client_->KNearestOfPoints(s->name(), ids, 2, true);
  ASSERT_TRUE(rp.ok()) << rp.status();
  ASSERT_EQ(rp->offsets.size(), 3001u);
  for (size_t i = 0; i < ids.size(); i += 11) {
    auto want = Rank(xy, At(xy, ids[i]), ids[i]);
    want.resize(2);
    ASSERT_EQ(Row(*rp, i), want) << "point " << ids[i];
  }
  // Mixed kinds of targets, and all_points, are refused.
  auto call = [&](const std::vector<v1::QueryRequest>& msgs) {
    grpc::ClientContext ctx;
    client_->Prepare(&ctx, s->name());
    auto st = client_->stub()->StreamQuery(&ctx);
    for (const auto& m : msgs) st->Write(m);
    st->WritesDone();
    v1::QueryResponse resp;
    while (st->Read(&resp)) {
    }
    return st->Finish();
  };
  v1::QueryRequest first;
  first.set_session(s->name());
  first.set_kind(v1::QUERY_KIND_NEAREST);
  first.mutable_positions()->add_xy(0.5);
  first.mutable_positions()->add_xy(0.5);
  v1::QueryRequest ids_part;
  ids_part.mutable_point_ids()->add_ids(3);
  EXPECT_EQ(call({first, ids_part}).error_code(),
            grpc::StatusCode::INVALID_ARGUMENT);
  v1::QueryRequest all = first;
  all.mutable_all_points();
  EXPECT_EQ(call({all}).error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(call({}).error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  // More targets than the server's --max_points (200000).
  v1::QueryRequest big;
  big.mutable_positions()->mutable_xy()->Resize(2 * 120000, 0.25);
  EXPECT_EQ(call({first, big, big}).error_code(),
            grpc::StatusCode::RESOURCE_EXHAUSTED);
  v1::QueryRequest odd;
  odd.mutable_positions()->add_xy(0.1);
  EXPECT_EQ(call({first, odd}).error_code(),
            grpc::StatusCode::INVALID_ARGUMENT);
  ASSERT_TRUE(client_->DeleteSession(s->name()).ok());
}

TEST_F(E2eTest, MetricsMove) {
  const std::string before =
      testing::HttpGet(server_->metrics_port(), "/metrics");
  ASSERT_NE(before.find("kinetri_sessions"), std::string::npos) << before;
  const std::vector<double> xy = Uniform(400, 40);
  auto s = client_->CreateSession(xy, v1::SessionOptions());
  ASSERT_TRUE(s.ok());
  auto st = client_->OpenSteps(s->name());
  ASSERT_TRUE((*st)->MoveBy(std::vector<double>(800, 0.0001)).ok());
  ASSERT_TRUE((*st)->Finish().ok());
  ASSERT_TRUE(client_->NearestOfAll(s->name()).ok());
  EXPECT_FALSE(client_->KNearestOfPoints(s->name(), {1}, -1, true).ok());
  const std::string after =
      testing::HttpGet(server_->metrics_port(), "/metrics");
  EXPECT_NE(after.find("kinetri_steps_total{path="), std::string::npos);
  EXPECT_NE(after.find(
                absl::StrCat("kinetri_update_duration_seconds_count{backend=\"",
                             kBackend, "\"} 1")),
            std::string::npos)
      << after;
  EXPECT_NE(
      after.find(absl::StrCat("kinetri_query_duration_seconds_count{backend=\"",
                              kBackend, "\",op=\"nearest\"} 1")),
      std::string::npos);
  EXPECT_NE(after.find("grpc_code=\"INVALID_ARGUMENT\""), std::string::npos);
  EXPECT_NE(after.find("kinetri_sessions 1"), std::string::npos);
}

// Every call is counted by the metrics interceptor (server/rpc_metrics.h),
// whatever path its handler returned by, with grpc_type from the method's
// proto definition (the handlers taking raw bytes are registered as
// bidirectional streams); methods the server does not have are counted
// under "unknown".
TEST_F(E2eTest, MetricsCountEveryCallWithItsProtoType) {
  const std::vector<double> xy = Uniform(300, 41);
  auto s = client_->CreateSession(xy, v1::SessionOptions());
  ASSERT_TRUE(s.ok());
  EXPECT_FALSE(client_->GetSession("sessions/no-such").ok());
  auto st = client_->OpenSteps(s->name());
  ASSERT_TRUE((*st)->MoveBy(std::vector<double>(600, 0.0001)).ok());
  ASSERT_TRUE((*st)->Finish().ok());
  ASSERT_TRUE(client_->NearestOfAll(s->name()).ok());
  auto channel = grpc::CreateChannel(server_->target(),
                                     grpc::InsecureChannelCredentials());
  grpc::GenericStub generic(channel);
  EXPECT_EQ(
      testing::SendRaw(generic, "/kinetri.v1.KinetriService/NoSuchMethod", {""})
          .error_code(),
      grpc::StatusCode::UNIMPLEMENTED);
  const std::string m = testing::HttpGet(server_->metrics_port(), "/metrics");
  auto handled = [](const char* code, const char* method, const char* type) {
    return absl::StrCat("grpc_server_handled_total{grpc_code=\"", code,
                        "\",grpc_method=\"", method,
                        "\",grpc_service=\"kinetri.v1.KinetriService\","
                        "grpc_type=\"",
                        type, "\"} ");
  };
  for (const std::string& line :
       {handled("OK", "CreateSession", "client_stream") + "1",
        handled("NOT_FOUND", "GetSession", "unary") + "1",
        handled("OK", "StreamSteps", "bidi_stream") + "1",
        handled("OK", "Query", "server_stream") + "1",
        std::string("grpc_server_started_total{grpc_method=\"Query\","
                    "grpc_service=\"kinetri.v1.KinetriService\","
                    "grpc_type=\"server_stream\"} 1"),
        std::string("grpc_server_handling_seconds_count{grpc_method=\""
                    "StreamSteps\",grpc_service=\"kinetri.v1.KinetriService"
                    "\",grpc_type=\"bidi_stream\"} 1")}) {
    EXPECT_NE(m.find(line + "\n"), std::string::npos) << line << "\n" << m;
  }
  EXPECT_NE(m.find("grpc_server_handled_total{grpc_code=\"UNIMPLEMENTED\","
                   "grpc_method=\"unknown\",grpc_service=\"unknown\","
                   "grpc_type=\"unknown\"} 1\n"),
            std::string::npos)
      << m;
  EXPECT_EQ(m.find("NoSuchMethod"), std::string::npos);
  ASSERT_TRUE(client_->DeleteSession(s->name()).ok());
}

// A SIGTERM that comes as soon as the server has said it listens drains it
// (exit 0). The handlers used to be installed after that line: a CI run
// caught the server killed by the signal (status 15) in GracefulShutdown.
TEST(E2eShutdown, SigtermRightAfterListeningDrains) {
  for (int i = 0; i < 10; ++i) {
    testing::ServerProcess server(
        KINETRI_SERVER_BINARY,
        {"--drain_delay_seconds=0", "--shutdown_grace_seconds=0"});
    ASSERT_TRUE(server.ok());
    EXPECT_EQ(server.Stop(), 0) << "run " << i;
  }
}

TEST(E2eShutdown, HealthTurnsNotServingWhileDraining) {
  testing::ServerProcess server(KINETRI_SERVER_BINARY,
                                {"--drain_delay_seconds=3"});
  ASSERT_TRUE(server.ok());
  // The whole server ("") and the service by name answer alike.
  const std::string kService = "kinetri.v1.KinetriService";
  EXPECT_EQ(testing::HealthStatus(server.target()), 1);
  EXPECT_EQ(testing::HealthStatus(server.target(), kService), 1);
  EXPECT_EQ(testing::HealthStatus(server.target(), "no.such.Service"), -1);
  server.Signal(SIGTERM);
  std::this_thread::sleep_for(std::chrono::milliseconds(800));
  EXPECT_EQ(testing::HealthStatus(server.target()), 2);
  EXPECT_EQ(testing::HealthStatus(server.target(), kService), 2);
  EXPECT_EQ(server.Stop(), 0);
}

// A step resent under the request_id it was applied with (its
// acknowledgement was lost) gets the original acknowledgement and is not
// applied twice; another request_id, or none, is refused as before.
TEST_F(E2eTest, ResentStepsAreIdempotent) {
  std::vector<double> xy = Uniform(500, 21);
  auto s = client_->CreateSession(xy, v1::SessionOptions(), "idem");
  ASSERT_TRUE(s.ok()) << s.status();
  std::vector<double> d(xy.size());
  std::mt19937_64 rng(5);
  std::normal_distribution<double> g(0.0, 0.01);
  for (double& v : d) v = g(rng);
  auto first = client_->OpenSteps(s->name());
  ASSERT_TRUE(first.ok());
  (*first)->SetNextRequestId("sim-7/step-1");
  auto ack = (*first)->MoveBy(d);
  ASSERT_TRUE(ack.ok()) << ack.status();
  ASSERT_TRUE((*first)->Finish().ok());
  for (int resend = 0; resend < 2; ++resend) {
    auto again = client_->OpenSteps(s->name(), 1);
    ASSERT_TRUE(again.ok());
    (*again)->SetNextRequestId("sim-7/step-1");
    auto replay = (*again)->MoveBy(d);
    ASSERT_TRUE(replay.ok()) << replay.status();
    EXPECT_EQ(replay->step(), 1u);
    EXPECT_EQ(replay->stats().delaunay_flips(), ack->stats().delaunay_flips());
    EXPECT_EQ(replay->stats().path(), ack->stats().path());
    // The stream goes on with the next step.
    EXPECT_EQ((*again)->next_step(), 2u);
    ASSERT_TRUE((*again)->Finish().ok());
  }
  auto mesh = client_->Export(s->name());
  ASSERT_TRUE(mesh.ok());
  EXPECT_EQ(mesh->step, 1u);
  for (size_t i = 0; i < xy.size(); ++i) {
    ASSERT_EQ(mesh->xy[i], xy[i] + d[i]) << "applied twice? value " << i;
  }
  for (const std::string other : {"sim-7/step-x", ""}) {
    auto stream = client_->OpenSteps(s->name(), 1);
    ASSERT_TRUE(stream.ok());
    (*stream)->SetNextRequestId(other);
    auto refused = (*stream)->MoveBy(d);
    EXPECT_EQ(refused.status().code(), absl::StatusCode::kFailedPrecondition)
        << "request_id \"" << other << "\": " << refused.status();
  }
}

// Rows with more results than fit in one message are split across chunks
// and put back together by the client: the same answer, whatever the
// chunk sizes.
TEST_F(E2eTest, RowsSplitAcrossChunks) {
  auto s = client_->CreateSession(Uniform(400, 31), v1::SessionOptions(),
                                  "split-rows");
  ASSERT_TRUE(s.ok()) << s.status();
  for (const v1::QueryKind kind :
       {v1::QUERY_KIND_K_NEAREST, v1::QUERY_KIND_RADIUS}) {
    v1::QueryRequest q;
    q.set_session(s->name());
    q.set_kind(kind);
    q.set_k(120);
    q.set_radius(0.3);
    q.set_max_results_per_row(90);  // radius rows get cut (and flagged)
    q.set_include_distances(true);
    q.set_exclude_self(true);
    for (uint32_t id : {0u, 7u, 99u, 300u}) q.mutable_point_ids()->add_ids(id);
    auto whole = client_->Query(q);
    ASSERT_TRUE(whole.ok()) << whole.status();
    for (const v1::AnswerEncoding encoding :
         {v1::ANSWER_ENCODING_VARINT, v1::ANSWER_ENCODING_FIXED}) {
      q.set_encoding(encoding);
      for (const uint32_t per : {1u, 7u, 64u, 121u}) {
        for (const uint32_t rows : {1u, 3u}) {
          q.set_results_per_chunk(per);
          q.set_rows_per_chunk(rows);
          auto split = client_->Query(q);
          ASSERT_TRUE(split.ok()) << split.status();
          const std::string at = absl::StrCat(encoding, " ", per, " ", rows);
          EXPECT_EQ(split->offsets, whole->offsets) << at;
          EXPECT_EQ(split->ids, whole->ids) << at;
          EXPECT_EQ(split->distances, whole->distances) << at;
          EXPECT_EQ(split->truncated_rows, whole->truncated_rows) << at;
        }
      }
    }
    q.clear_encoding();
    q.clear_results_per_chunk();
    q.clear_rows_per_chunk();
    if (kind == v1::QUERY_KIND_RADIUS) {
      EXPECT_FALSE(whole->truncated_rows.empty());
    }
  }
}

// The server answers in the encoding asked for (read here with protobuf's
// parser, not the client's, which reads either): varints by default,
// fixed-width fields for ANSWER_ENCODING_FIXED, for sequential and client
// ids; an encoding it does not know is answered in varints.
TEST_F(E2eTest, AnswersComeInTheAskedEncoding) {
  const std::vector<double> xy = Uniform(300, 17);
  std::vector<uint64_t> cid(300);
  for (size_t i = 0; i < cid.size(); ++i) cid[i] = (uint64_t{1} << 50) + i;
  auto seq = client_->CreateSession(xy, v1::SessionOptions(), "enc-seq");
  ASSERT_TRUE(seq.ok()) << seq.status();
  auto by_cid =
      client_->CreateSessionWithIds(xy, cid, v1::SessionOptions(), "enc-cid");
  ASSERT_TRUE(by_cid.ok()) << by_cid.status();
  auto chunks = [&](const v1::QueryRequest& q, grpc::Status* status) {
    grpc::ClientContext ctx;
    client_->Prepare(&ctx, q.session());
    auto reader = client_->stub()->Query(&ctx, q);
    std::vector<v1::QueryResponse> out;
    v1::QueryResponse m;
    while (reader->Read(&m)) out.push_back(m);
    *status = reader->Finish();
    return out;
  };
  for (const bool client_ids : {false, true}) {
    v1::QueryRequest q;
    q.set_session(client_ids ? by_cid->name() : seq->name());
    q.set_kind(v1::QUERY_KIND_K_NEAREST);
    q.set_k(4);
    q.set_include_distances(true);
    q.mutable_all_points();
    q.set_rows_per_chunk(70);  // several chunks
    std::vector<std::vector<v1::QueryResponse>> answers;
    for (const v1::AnswerEncoding encoding :
         {v1::ANSWER_ENCODING_UNSPECIFIED, v1::ANSWER_ENCODING_VARINT,
          v1::ANSWER_ENCODING_FIXED}) {
      q.set_encoding(encoding);
      grpc::Status st;
      answers.push_back(chunks(q, &st));
      ASSERT_TRUE(st.ok()) << st.error_message();
      ASSERT_EQ(answers.back().size(), 5u);  // 300 rows, 70 per chunk
      const bool fixed = encoding == v1::ANSWER_ENCODING_FIXED;
      for (const v1::QueryResponse& m : answers.back()) {
        EXPECT_EQ(m.offsets_size() > 0, !fixed);
        EXPECT_EQ(m.fixed_offsets_size() > 0, fixed);
        EXPECT_EQ(m.ids_size() > 0, !fixed && !client_ids);
        EXPECT_EQ(m.fixed_ids_size() > 0, fixed && !client_ids);
        EXPECT_EQ(m.client_ids_size() > 0, !fixed && client_ids);
        EXPECT_EQ(m.fixed_client_ids_size() > 0, fixed && client_ids);
      }
    }
    // The same rows in each encoding.
    for (size_t c = 0; c < 5; ++c) {
      const v1::QueryResponse& v = answers[1][c];
      const v1::QueryResponse& f = answers[2][c];
      EXPECT_EQ(answers[0][c].SerializeAsString(), v.SerializeAsString());
      EXPECT_TRUE(std::equal(v.offsets().begin(), v.offsets().end(),
                             f.fixed_offsets().begin(),
                             f.fixed_offsets().end()));
      EXPECT_TRUE(std::equal(v.ids().begin(), v.ids().end(),
                             f.fixed_ids().begin(), f.fixed_ids().end()));
      EXPECT_TRUE(std::equal(v.client_ids().begin(), v.client_ids().end(),
                             f.fixed_client_ids().begin(),
                             f.fixed_client_ids().end()));
      EXPECT_TRUE(std::equal(v.distances().begin(), v.distances().end(),
                             f.distances().begin(), f.distances().end()));
      EXPECT_EQ(v.first_row(), f.first_row());
    }
  }
  // An encoding the server does not know (a newer client's): varints.
  v1::QueryRequest newer;
  newer.set_session(seq->name());
  newer.set_kind(v1::QUERY_KIND_NEAREST);
  newer.mutable_all_points();
  newer.set_encoding(static_cast<v1::AnswerEncoding>(7));
  grpc::Status st;
  const std::vector<v1::QueryResponse> got = chunks(newer, &st);
  ASSERT_TRUE(st.ok()) << st.error_message();
  ASSERT_EQ(got.size(), 1u);
  EXPECT_EQ(got[0].ids_size(), 300);
  EXPECT_EQ(got[0].fixed_ids_size(), 0);
}

// Paging tokens are opaque (no session name shows through) and only tokens
// the server made are taken.
TEST_F(E2eTest, ListSessionsPagesWithOpaqueTokens) {
  std::set<std::string> created;
  for (int i = 0; i < 4; ++i) {  // the fixture allows 4 sessions
    auto s =
        client_->CreateSession(testing::UniformXY(20, i), v1::SessionOptions(),
                               "page-" + std::to_string(i));
    ASSERT_TRUE(s.ok()) << s.status();
    created.insert(s->name());
  }
  std::set<std::string> listed;
  std::string token;
  int pages = 0;
  do {
    grpc::ClientContext ctx;
    v1::ListSessionsRequest req;
    req.set_page_size(3);
    req.set_page_token(token);
    v1::ListSessionsResponse resp;
    ASSERT_TRUE(client_->stub()->ListSessions(&ctx, req, &resp).ok());
    for (const auto& s : resp.sessions()) {
      EXPECT_TRUE(listed.insert(s.name()).second) << "listed twice";
    }
    token = resp.next_page_token();
    EXPECT_EQ(token.find("page-"), std::string::npos) << token;
    ++pages;
  } while (!token.empty());
  EXPECT_EQ(listed, created);
  EXPECT_EQ(pages, 2);
  for (const std::string bad : {"sessions/page-1", "page-1", "%%%"}) {
    grpc::ClientContext ctx;
    v1::ListSessionsRequest req;
    req.set_page_token(bad);
    v1::ListSessionsResponse resp;
    const grpc::Status st = client_->stub()->ListSessions(&ctx, req, &resp);
    EXPECT_EQ(st.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << bad;
  }
}

TEST_F(E2eTest, GracefulShutdown) { EXPECT_EQ(server_->Stop(), 0); }

}  // namespace
}  // namespace kinetri
