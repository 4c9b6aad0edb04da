// Batched proximity queries on the Delaunay graph, results in CSR form.
//
// Order: for a query position q, points are ranked by exact squared distance
// to q; ties between distinct positions go to the larger x, then the larger y
// (CompareCloser: the distance order seen from q nudged by an infinitesimal),
// and ties between coincident points go to the smaller id. Every query kind
// returns exactly the first points of this order, so results are unique and
// a brute-force scan with the same comparator reproduces them.
//
// Algorithms (all read-only, parallel over queries):
//  * nearest site of q: greedy walk on the Delaunay graph from a hint; a
//    Delaunay vertex that is not the nearest site always has a neighbour that
//    is strictly closer (also under the nudged order), so the walk ends at it;
//  * k nearest: best-first expansion from the nearest site: the (i+1)-th
//    closest site is adjacent to one of the first i (each site has a strictly
//    closer neighbour unless it is the first), so taking sites closest
//    first from the frontier yields them in order; the frontier is a short
//    sorted list that drops candidates which can no longer be taken;
//  * fixed radius (FRNN): breadth-first search from the nearest site over
//    Delaunay neighbours that lie in the disk. It finds every site in the
//    disk because those sites are connected through the disk: a site v in
//    the disk other than the first one has a Delaunay neighbour strictly
//    before it in the order above (greedy property), hence at distance
//    <= |qv| <= r, so following such neighbours from v stays in the disk and
//    ends at the first site. Visited sites are marked with per-thread epoch
//    stamps (constant-time check, no linear "visited?" scan). (A reverse
//    search needing no marks at all - descend to w only when w's closest
//    neighbour is the current site - was implemented first: it recomputes
//    each candidate's closest neighbour, a cost quadratic in vertex degree,
//    and measured 2.8x slower for 32-neighbour radius queries on 10K uniform
//    points, so the CPU executor uses marks.)
//    When disks are expected to hold several sites (RowOptions::Plan), the
//    sites of a disk come instead from a cell index of side r built for the
//    batch (core/cell_index.h): the cells that meet the disk's bounding
//    square, scanned in contiguous memory, each site tested with the same
//    exact predicate. Rows are identical either way.
//  * k nearest, large batches on evenly spread sites: the sites of a disk
//    from a cell index of about two sites per cell, the disk's radius
//    grown until k sites lie in it for certain (starting from the last
//    row's k-th distance), then sorted in the exact order; every point
//    before the k-th is in the disk. Rows are identical to the graph's.
#ifndef KINETRI_CORE_QUERIES_H_
#define KINETRI_CORE_QUERIES_H_

#include <cstdint>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/types/span.h"
#include "core/cancel.h"
#include "core/query_types.h"
#include "core/triangulation.h"
#include "core/vec2.h"

namespace kinetri::core {

// Nearest other point of every point (the note's all-points query). A point
// with no other point gets an empty row. Duplicates find each other at 0.
// Of `options` only recycle applies.
absl::StatusOr<NeighborLists> AllNearestNeighbors(const Triangulation& t,
                                                  RowOptions options = {});

// k nearest points of each position, closest first, with distances. Of
// `options` only the plan, batch_queries and recycle apply: kAuto scans a cell
// index for large batches on evenly spread sets, kGraph always expands
// over the graph, kCells always scans cells (rows are identical).
absl::StatusOr<NeighborLists> KNearest(const Triangulation& t,
                                       absl::Span<const Vec2> queries, int k,
                                       QueryLimits limits = {},
                                       RowOptions options = {});

// k nearest points of each given point; exclude_self drops the point itself
// (its coincident duplicates are still reported). `options` as KNearest.
absl::StatusOr<NeighborLists> KNearestOfPoints(const Triangulation& t,
                                               absl::Span<const uint32_t> ids,
                                               int k, bool exclude_self,
                                               QueryLimits limits = {},
                                               RowOptions options = {});

// All points within distance r (inclusive) of each position, closest first
// (unless options say otherwise), at most max_results per row (0 =
// unlimited; a cut row is flagged).
absl::StatusOr<NeighborLists> WithinRadius(const Triangulation& t,
                                           absl::Span<const Vec2> queries,
                                           double r, uint32_t max_results,
                                           QueryLimits limits = {},
                                           RowOptions options = {});

absl::StatusOr<NeighborLists> WithinRadiusOfPoints(
    const Triangulation& t, absl::Span<const uint32_t> ids, double r,
    bool exclude_self, uint32_t max_results, QueryLimits limits = {},
    RowOptions options = {});

// The nearest point of each position (k = 1).
absl::StatusOr<NeighborLists> Nearest(const Triangulation& t,
                                      absl::Span<const Vec2> queries);

// The argument checks every executor applies (INVALID_ARGUMENT or NOT_FOUND
// naming the field and index).
absl::Status CheckQueryPositions(absl::Span<const Vec2> queries);
absl::Status CheckQueryIds(const Triangulation& t,
                           absl::Span<const uint32_t> ids);
absl::Status CheckQueryRadius(double r);
absl::Status CheckQueryK(int k);

}  // namespace kinetri::core

#endif  // KINETRI_CORE_QUERIES_H_
