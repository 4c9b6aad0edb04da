// Cancels client-streaming calls that stop sending.
//
// The synchronous gRPC API has no timed Read: a step or creation stream
// whose client stays connected but sends nothing would hold its server
// thread (and what it buffered) forever. Each such handler holds a
// Registration and touches it on every message; a background thread
// cancels (ServerContext::TryCancel) calls idle longer than the timeout, so
// their blocked Read returns and the handler ends with CANCELLED.
#ifndef KINETRI_SERVER_IDLE_WATCHDOG_H_
#define KINETRI_SERVER_IDLE_WATCHDOG_H_

#include <grpcpp/server_context.h>

#include <atomic>
#include <chrono>
#include <cstdint>
#include <thread>

#include "absl/container/flat_hash_map.h"
#include "absl/synchronization/mutex.h"

namespace kinetri::server {

class IdleWatchdog {
 public:
  // timeout <= 0: never cancels (registrations are still cheap no-ops).
  explicit IdleWatchdog(std::chrono::milliseconds timeout);
  ~IdleWatchdog();
  IdleWatchdog(const IdleWatchdog&) = delete;
  IdleWatchdog& operator=(const IdleWatchdog&) = delete;

  // Watches one call while it lives.
  class Registration {
   public:
    Registration(IdleWatchdog* dog, grpc::ServerContext* ctx);
    ~Registration();
    Registration(const Registration&) = delete;
    Registration& operator=(const Registration&) = delete;
    // The call made progress (a message arrived).
    void Touch();
    // True once the watchdog cancelled this call for idling.
    bool timed_out() const;

   private:
    IdleWatchdog* dog_;
    grpc::ServerContext* ctx_;
  };

  uint64_t cancelled_total() const { return cancelled_total_.load(); }

 private:
  struct Entry {
    std::chrono::steady_clock::time_point last;
    bool timed_out = false;
  };
  void Loop();

  const std::chrono::milliseconds timeout_;
  mutable absl::Mutex mu_;
  absl::flat_hash_map<grpc::ServerContext*, Entry> calls_ ABSL_GUARDED_BY(mu_);
  bool stop_ ABSL_GUARDED_BY(mu_) = false;
  std::atomic<uint64_t> cancelled_total_{0};
  std::thread thread_;
};

}  // namespace kinetri::server

#endif  // KINETRI_SERVER_IDLE_WATCHDOG_H_
