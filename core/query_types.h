// What a batched proximity query returns and what bounds it, shared by
// every query executor (core/queries.h on the host, the device executor's
// queries in core/device/): rows in CSR form, the row options and the
// limits, and the one refusal a passed limit gets.
#ifndef KINETRI_CORE_QUERY_TYPES_H_
#define KINETRI_CORE_QUERY_TYPES_H_

#include <cstddef>
#include <cstdint>
#include <functional>
#include <vector>

#include "absl/status/status.h"
#include "core/cancel.h"

namespace kinetri::core {

// Compressed sparse rows: the neighbours of query i are
// ids[offsets[i] .. offsets[i+1]) with matching distances, closest first.
struct NeighborLists {
  std::vector<uint64_t> offsets;   // size = queries + 1
  std::vector<uint32_t> ids;       // external point ids
  std::vector<double> distances;   // Euclidean, rounded to double
  std::vector<uint8_t> truncated;  // per query: max_results cut the row

  size_t num_queries() const {
    return offsets.empty() ? 0 : offsets.size() - 1;
  }
  size_t row_size(size_t i) const { return offsets[i + 1] - offsets[i]; }
};

// What radius rows carry. The closest-first order costs a sort per row and
// the distances a square root per result; callers that need only the set of
// neighbours ("who is within r of whom") can drop either. Rows cut by
// max_results are always the closest points, whatever the order asked for.
struct RowOptions {
  bool closest_first = true;  // false: rows in traversal order
  bool distances = true;      // false: NeighborLists::distances stays empty
  // How the host executors find the sites in a disk (same answers either
  // way): kAuto picks by the expected number of neighbours per disk;
  // kGraph walks the Delaunay graph from the nearest site; kCells scans a
  // cell index of side r built for the call (contiguous memory: faster
  // once disks hold more than a few sites). The device executor always
  // walks the graph.
  enum class Plan { kAuto, kGraph, kCells };
  Plan plan = Plan::kAuto;
  // The whole batch's number of queries when it is asked in blocks (the
  // server does): kAuto plans for the batch, not for one block.
  uint64_t batch_queries = 0;
  // An earlier answer whose memory the host executors may build this one
  // in (it is left empty or in an unspecified state). A loop that asks the
  // same query every step passes the last step's answer: a fresh answer's
  // memory is first touched while the rows are written (one page fault per
  // 4 KiB: about 3 ms of a 16.7 ms 8-NN of all 100K points, 9.6 MB).
  NeighborLists* recycle = nullptr;
};

struct QueryLimits {
  // Total results above this fail with RESOURCE_EXHAUSTED (0 = no limit).
  // The limit is checked while rows are built (a row stops as soon as it
  // would pass it), so a refused query costs about the limit, not its
  // answer.
  uint64_t max_total_results = 0;
  // Polled per row and every few thousand sites inside a row; when it fires
  // the query stops and returns CANCELLED or DEADLINE_EXCEEDED.
  const CancelToken* cancel = nullptr;
  // Optional: asked before the rows kept so far pass what it last granted,
  // with the new count of results rounded up to a multiple of kAdmitStep
  // (calls come one at a time, with growing counts). Threads count their
  // rows' results in batches, so the count asked for includes up to
  // kCountBatch results per thread not counted yet. A non-OK answer stops
  // the query, which returns it. The server reserves an answer's memory
  // from its budget this way: the reservation grows with the answer
  // instead of following a guess made before it. An answer whose size is
  // known before it is built (k-NN of a set with more than k points: k per
  // query) is admitted whole, in one call, before anything is allocated.
  std::function<absl::Status(uint64_t results)> admit;
  static constexpr uint64_t kAdmitStep = uint64_t{1} << 18;
  // How many results a thread keeps before it adds them to the query's
  // shared count (rows of ~1 us each, counted one by one into one counter
  // from every thread, cost 4-8 % of a batch of 8-neighbour radius rows).
  static constexpr uint64_t kCountBatch = 1024;
};

// RESOURCE_EXHAUSTED for a query whose rows passed max_total_results: the
// same message from every executor.
absl::Status ResultLimitError(uint64_t max_total_results);

}  // namespace kinetri::core

#endif  // KINETRI_CORE_QUERY_TYPES_H_
