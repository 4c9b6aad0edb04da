// How many queries the device executor runs per block
// (core/device/device_queries.inl). Between blocks the host polls
// cancellation and checks the total limit, so a block should take about
// kTargetSeconds; its size adapts to the times the blocks took.
//
// On CPU threads (the emulated backend) a block's time is all work: a
// block doubles while it takes under half the target and halves while it
// takes over twice the target. On a GPU each block also pays a fixed cost
// (a dozen synchronous device calls; on the first GPU runs about a
// millisecond each, docs/DEVICE.md), and a block whose fixed cost alone was
// over half the target never grew past its first 2 queries. There a block
// also doubles when its time is mostly that fixed cost: after the first
// block, or when it took well under twice its half-size predecessor's time,
// as long as it stays under kLimitSeconds (or twice the quickest block's
// time, where the fixed cost alone is over that); and it halves only when it
// took over twice the quickest block's time too (halving cannot shorten a block
// that is all fixed cost). Host code only, so it is tested without a GPU.
//
// The device's fill (GPU only): the queries that occupy every
// multiprocessor once. Thrust's for_each runs 256 threads of 2 elements per
// CUDA block, so a block of up to 512 queries runs on one multiprocessor,
// and a block of 328 takes twice one of 164 (a thread takes its second
// query after its first). The third GPU lease saw the rule above stop
// there: 100K queries in blocks of about 164, each running on one of 132
// multiprocessors (docs/DEVICE.md). Below the fill a block takes about as
// long as at the fill (one query per thread, latency-bound), so on a GPU
// the first block is the fill and a block never halves below it;
// KINETRI_DEVICE_QUERY_BLOCK=N (read once per process) sets the first block
// instead, on CPU threads too (a test runs a whole batch as one block
// there). A long block is still stopped soon after cancellation: the
// query kernels read a stop word (device_queries.inl).
#ifndef KINETRI_CORE_DEVICE_BLOCK_SIZER_H_
#define KINETRI_CORE_DEVICE_BLOCK_SIZER_H_

#include <algorithm>
#include <cstddef>
#include <cstdlib>

namespace kinetri::core::device {

class BlockSizer {
 public:
  static constexpr size_t kFirstBlock = 2;
  static constexpr double kTargetSeconds = 0.008;
  static constexpr double kLimitSeconds = 0.025;

  // Blocks of at most max_block queries, the first of first_block queries
  // (0: kFirstBlock, or the fill on a GPU); fixed_cost_aware on a GPU,
  // whose blocks never halve below `fill` (0: none known) or a smaller
  // first block.
  BlockSizer(size_t max_block, bool fixed_cost_aware, size_t first_block = 0,
             size_t fill = 0)
      : max_(std::max<size_t>(1, max_block)),
        fixed_cost_aware_(fixed_cost_aware),
        floor_(
            fixed_cost_aware
                ? std::min({fill, first_block > 0 ? first_block : fill, max_})
                : 0),
        block_(std::min(first_block > 0 ? first_block
                                        : std::max(kFirstBlock,
                                                   fixed_cost_aware ? fill : 0),
                        max_)) {}

  // KINETRI_DEVICE_QUERY_BLOCK, or 0 where it is unset or not a number.
  static size_t FirstBlockFromEnvironment() {
    static const size_t first = [] {
      const char* v = std::getenv("KINETRI_DEVICE_QUERY_BLOCK");
      return v == nullptr ? size_t{0}
                          : static_cast<size_t>(std::strtoull(v, nullptr, 10));
    }();
    return first;
  }

  // The size of the next block.
  size_t size() const { return block_; }

  // The last block was cut to its first n queries (their results filled
  // the memory a block may take): the next one takes n, below the fill
  // too, so that the queries after a cut are not counted again and again.
  void CutTo(size_t n) { block_ = std::max<size_t>(1, std::min(n, max_)); }

  // A block of n queries took `seconds`: sets the next size.
  void Done(size_t n, double seconds) {
    min_seconds_ = std::min(min_seconds_, seconds);
    const bool fixed_cost_bound =
        fixed_cost_aware_ &&
        (last_n_ == 0 || (n >= 2 * last_n_ && seconds < 1.5 * last_seconds_));
    last_n_ = n;
    last_seconds_ = seconds;
    if (seconds < kTargetSeconds / 2 ||
        (fixed_cost_bound &&
         seconds < std::max(kLimitSeconds, 2 * min_seconds_))) {
      block_ = std::min(block_ * 2, max_);
    } else if (seconds > kTargetSeconds * 2 &&
               (!fixed_cost_aware_ || seconds > 2 * min_seconds_) &&
               block_ > 1 && block_ > floor_) {
      block_ = std::max(block_ / 2, std::max<size_t>(floor_, 1));
    }
  }

 private:
  size_t max_;
  bool fixed_cost_aware_;
  size_t floor_;  // a GPU's fill: no halving below it
  size_t block_;
  size_t last_n_ = 0;  // the previous block's size and seconds
  double last_seconds_ = 0.0;
  double min_seconds_ = 1e300;  // the quickest block (about its fixed cost)
};

}  // namespace kinetri::core::device

#endif  // KINETRI_CORE_DEVICE_BLOCK_SIZER_H_
