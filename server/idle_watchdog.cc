#include "server/idle_watchdog.h"

#include <algorithm>

namespace kinetri::server {

using Clock = std::chrono::steady_clock;

IdleWatchdog::IdleWatchdog(std::chrono::milliseconds timeout)
    : timeout_(timeout) {
  if (timeout_.count() > 0) thread_ = std::thread([this] { Loop(); });
}

IdleWatchdog::~IdleWatchdog() {
  {
    absl::MutexLock lock(&mu_);
    stop_ = true;
  }
  if (thread_.joinable()) thread_.join();
}

void IdleWatchdog::Loop() {
  // Checks a few times per timeout (at most every second).
  const auto period = std::min<std::chrono::milliseconds>(
      std::chrono::milliseconds(1000),
      std::max<std::chrono::milliseconds>(std::chrono::milliseconds(10),
                                          timeout_ / 4));
  absl::MutexLock lock(&mu_);
  while (!stop_) {
    mu_.AwaitWithTimeout(absl::Condition(&stop_), absl::FromChrono(period));
    if (stop_) break;
    const auto now = Clock::now();
    for (auto& [ctx, entry] : calls_) {
      if (!entry.timed_out && now - entry.last > timeout_) {
        entry.timed_out = true;
        ++cancelled_total_;
        ctx->TryCancel();
      }
    }
  }
}

IdleWatchdog::Registration::Registration(IdleWatchdog* dog,
                                         grpc::ServerContext* ctx)
    : dog_(dog), ctx_(ctx) {
  if (dog_->timeout_.count() <= 0) return;
  absl::MutexLock lock(&dog_->mu_);
  dog_->calls_[ctx_] = Entry{Clock::now(), false};
}

IdleWatchdog::Registration::~Registration() {
  if (dog_->timeout_.count() <= 0) return;
  absl::MutexLock lock(&dog_->mu_);
  dog_->calls_.erase(ctx_);
}

void IdleWatchdog::Registration::Touch() {
  if (dog_->timeout_.count() <= 0) return;
  absl::MutexLock lock(&dog_->mu_);
  auto it = dog_->calls_.find(ctx_);
  if (it != dog_->calls_.end()) it->second.last = Clock::now();
}

bool IdleWatchdog::Registration::timed_out() const {
  if (dog_->timeout_.count() <= 0) return false;
  absl::MutexLock lock(&dog_->mu_);
  auto it = dog_->calls_.find(ctx_);
  return it != dog_->calls_.end() && it->second.timed_out;
}

}  // namespace kinetri::server
