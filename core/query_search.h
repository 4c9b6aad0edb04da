// Per-query graph searches that need no visited marks and no heap memory,
// host+device (one query per CUDA thread; the CPU tests run the same code).
//
//  * RadiusSearch enumerates the sites within r of q by reverse search on
//    the Delaunay graph: the parent of a site w other than the nearest site
//    is its neighbour that comes first from q (FirstNeighbor), which is
//    strictly closer than w (greedy property, queries.h) and so lies in the
//    disk whenever w does. The parent links form a tree over the sites in
//    the disk rooted at the nearest site; the search walks that tree depth
//    first: after finishing a site it goes back to its parent and resumes
//    the parent's row after it, from a path of the last 16 steps down kept
//    on the thread's stack, or below that found again as the neighbour
//    that comes first. Each site in the disk is reported exactly once;
//    memory is O(1) per query.
//  * KNearestSearch finds the k first points of the exact order. For small
//    k it takes the sites best first from the nearest one, discovering
//    each from its parent (the same tree), with a candidate list of at
//    most k + 1 sites on the thread's stack. For large k it counts the
//    points in disks of growing radius (starting from the distance of the
//    farthest neighbour of the nearest site), and once a disk holds at
//    least k points (the query's own point excluded) it keeps the k first
//    of them in a bounded heap in the caller's buffer, sorted at the end. Every
//    point among the k first is no farther than the k-th point in the disk,
//    hence in the disk.
//
// Both need the neighbour rows of a query view (TriangulationView::adj).
#ifndef KINETRI_CORE_QUERY_SEARCH_H_
#define KINETRI_CORE_QUERY_SEARCH_H_

#include <cstdint>
#include <type_traits>

#include "core/hd.h"
#include "core/predicates.h"
#include "core/query_walks.h"
#include "core/triangulation_view.h"

namespace kinetri::core {

// Site w lies in the closed disk of radius r around q (exact).
KINETRI_HD inline bool InDisk(const TriangulationView& v, const Vec2& q,
                              double r, uint32_t w) {
  const double d2 = SquaredDistance(q, v.pos[w]);
  const double rr = r * r;
  const double tol = internal::kDistErrBound * (d2 + rr);
  if (d2 < rr - tol) return true;
  if (d2 > rr + tol) return false;
  return CompareDistanceToRadius(q, v.pos[w], r) <= 0;
}

// emit(site), and whether the search goes on (an emit returning bool may
// stop it).
template <typename Emit>
KINETRI_HD bool EmitAndGoOn(Emit& emit, uint32_t site) {
  if constexpr (std::is_void_v<decltype(emit(site))>) {
    emit(site);
    return true;
  } else {
    return emit(site);
  }
}

// Calls emit(site) for every site within r of q; root must be the nearest
// site of q (WalkToNearestSite). Returns the number of sites emitted. An
// emit that returns bool stops the search by returning false.
template <typename Emit>
KINETRI_HD uint32_t RadiusSearch(const TriangulationView& v, const Vec2& q,
                                 double r, uint32_t root, Emit&& emit) {
  if (!InDisk(v, q, r, root)) return 0;
  uint32_t count = 1;
  if (!EmitAndGoOn(emit, root)) return count;
  uint32_t u = root;
  const uint32_t* it = v.RowBegin(u);
  // The last kPath steps down the tree (parent, where its row resumes), so
  // going back up needs no search; deeper paths forget their oldest steps,
  // which are found again from the geometry.
  constexpr uint32_t kPath = 16;
  uint32_t path_site[kPath];
  const uint32_t* path_row[kPath];
  uint32_t top = 0, held = 0;
  while (true) {
    bool descended = false;
    const double du = SquaredDistance(q, v.pos[u]);
    for (; it != v.RowEnd(u); ++it) {
      const uint32_t w = *it;
      if (w == root) continue;
      // A child is farther than its parent (clear cases in double).
      const double dw = SquaredDistance(q, v.pos[w]);
      if (dw < du - internal::kDistErrBound * (du + dw)) continue;
      if (!InDisk(v, q, r, w)) continue;
      if (FirstNeighbor(v, q, w, /*include_self=*/false) != u) continue;
      ++count;
      if (!EmitAndGoOn(emit, w)) return count;
      path_site[top] = u;
      path_row[top] = it + 1;
      top = (top + 1) % kPath;
      if (held < kPath) ++held;
      u = w;
      it = v.RowBegin(u);
      descended = true;
      break;
    }
    if (descended) continue;
    if (u == root) return count;
    if (held > 0) {  // back to the parent, from the path
      top = (top + kPath - 1) % kPath;
      --held;
      u = path_site[top];
      it = path_row[top];
      continue;
    }
    // Back to the parent, just after u in its row.
    const uint32_t p = FirstNeighbor(v, q, u, false);
    it = v.RowBegin(p);
    while (*it != u) ++it;
    ++it;
    u = p;
  }
}

// RadiusSearch for disks of at most kSmallDiskSites sites: breadth first
// from the nearest site (the sites in a disk around q holding the nearest
// site are connected through sites in the disk: each has a neighbour closer
// to q), with the sites seen, in the disk or on its rim, in a small hash
// table on the thread's stack, so each site costs one scan of its row and
// no parent tests (RadiusSearch tests each neighbour's parent: a scan of
// the neighbour's row). The sites are emitted only once the disk is known
// to fit: false (nothing emitted) when it does not, and the caller goes on
// with RadiusSearch. *count: the sites emitted.
inline constexpr uint32_t kSmallDiskSites = 48;
template <typename Emit>
KINETRI_HD bool SmallDiskSearch(const TriangulationView& v, const Vec2& q,
                                double r, uint32_t root, Emit&& emit,
                                uint32_t* count) {
  *count = 0;
  if (!InDisk(v, q, r, root)) return true;
  constexpr uint32_t kTable = 128;  // at most 3/4 full
  uint32_t seen[kTable];
  for (uint32_t i = 0; i < kTable; ++i) seen[i] = kNoVertex;
  uint32_t seen_count = 0;
  // Whether w was not seen before (and is now); false also when the table
  // is full (the caller then stops).
  auto first_sight = [&](uint32_t w) {
    uint32_t h = (w * 2654435761u) >> 25;  // 7 bits: kTable
    while (seen[h] != kNoVertex) {
      if (seen[h] == w) return false;
      h = (h + 1) & (kTable - 1);
    }
    seen[h] = w;
    ++seen_count;
    return true;
  };
  uint32_t sites[kSmallDiskSites];
  uint32_t n = 0;
  first_sight(root);
  sites[n++] = root;
  for (uint32_t head = 0; head < n; ++head) {
    const uint32_t u = sites[head];
    for (const uint32_t* it = v.RowBegin(u); it != v.RowEnd(u); ++it) {
      if (seen_count >= kTable * 3 / 4) return false;
      const uint32_t w = *it;
      if (!first_sight(w) || !InDisk(v, q, r, w)) continue;
      if (n == kSmallDiskSites) return false;
      sites[n++] = w;
    }
  }
  for (uint32_t i = 0; i < n; ++i) {
    ++*count;
    if (!EmitAndGoOn(emit, sites[i])) break;
  }
  return true;
}

// Every site within r of q, as RadiusSearch, by SmallDiskSearch where the
// disk is small. Returns the number of sites emitted.
template <typename Emit>
KINETRI_HD uint32_t DiskSearch(const TriangulationView& v, const Vec2& q,
                               double r, uint32_t root, Emit&& emit) {
  uint32_t count;
  if (SmallDiskSearch(v, q, r, root, emit, &count)) return count;
  return RadiusSearch(v, q, r, root, emit);
}

// Number of points of site s other than `self` (an external id, or
// kNoVertex): O(1) with the view's site member rows.
KINETRI_HD inline uint32_t PointsOfSite(const TriangulationView& v, uint32_t s,
                                        uint32_t self) {
  if (v.dup_next[s] == kNoVertex) return v.ext_of_int[s] != self ? 1u : 0u;
  if (v.site_member_offsets != nullptr) {
    uint32_t n = v.site_member_offsets[s + 1] - v.site_member_offsets[s];
    if (self != kNoVertex && v.rep[v.int_of_ext[self]] == s) --n;
    return n;
  }
  uint32_t n = 0;
  for (uint32_t p = s; p != kNoVertex; p = v.dup_next[p]) {
    if (v.ext_of_int[p] != self) ++n;
  }
  return n;
}

// A stop check that never stops (CountPointsWithin's default).
struct NeverStop {
  KINETRI_HD bool operator()() const { return false; }
};

// Number of points (not sites) within r of q, `self` (an external id, or
// kNoVertex) excluded; the search stops once the count reaches `cap`, or
// when stop() returns true after a site (the count is then short).
template <typename Stop = NeverStop>
KINETRI_HD uint32_t CountPointsWithin(const TriangulationView& v, const Vec2& q,
                                      double r, uint32_t root, uint32_t self,
                                      uint32_t cap = UINT32_MAX,
                                      Stop&& stop = {}) {
  uint32_t points = 0;
  DiskSearch(v, q, r, root, [&](uint32_t s) {
    const uint32_t n = PointsOfSite(v, s, self);
    points = n > cap - points ? cap : points + n;
    return points < cap && !stop();
  });
  return points;
}

// Up to this k, KNearestSearch searches best first (KNearestBestFirst);
// above, it counts disks of growing radius and keeps the rows in a heap.
inline constexpr uint32_t kKnnBestFirstMax = 32;

// One entry of a k-NN answer: internal point id and squared distance.
struct KnnEntry {
  uint32_t point;
  double d2;
};

// Entry x comes before entry y: the exact order from q, coincident points
// by external id.
struct EntryOrder {
  const TriangulationView& v;
  Vec2 q;
  KINETRI_HD bool operator()(const KnnEntry& x, const KnnEntry& y) const {
    const int c =
        CompareCloserCached(q, v.pos[x.point], x.d2, v.pos[y.point], y.d2);
    return c < 0 || (c == 0 && v.ext_of_int[x.point] < v.ext_of_int[y.point]);
  }
};

// The entry at i sinks to its place in the max-heap a[0..end) (by less).
template <typename Less>
KINETRI_HD void SiftDown(KnnEntry* a, uint32_t i, uint32_t end,
                         const Less& less) {
  const KnnEntry x = a[i];
  while (true) {
    uint32_t c = 2 * i + 1;
    if (c >= end) break;
    if (c + 1 < end && less(a[c], a[c + 1])) ++c;
    if (!less(x, a[c])) break;
    a[i] = a[c];
    i = c;
  }
  a[i] = x;
}

// The max-heap a[0..n) into ascending order (each top to the end of the
// shrinking heap).
template <typename Less>
KINETRI_HD void SortHeap(KnnEntry* a, uint32_t n, const Less& less) {
  for (uint32_t end = n; end > 1; --end) {
    const KnnEntry top = a[0];
    a[0] = a[end - 1];
    a[end - 1] = top;
    SiftDown(a, 0, end - 1, less);
  }
}

// Sorts row[0..n) closest first (EntryOrder) in place, without memory: by
// insertion for short rows, by heap sort (O(n log n)) above, so one
// thread sorts a row of thousands too.
KINETRI_HD inline void SortRow(const TriangulationView& v, const Vec2& q,
                               KnnEntry* row, uint32_t n) {
  const EntryOrder less{v, q};
  if (n <= 48) {
    for (uint32_t i = 1; i < n; ++i) {
      const KnnEntry x = row[i];
      uint32_t j = i;
      for (; j > 0 && less(x, row[j - 1]); --j) row[j] = row[j - 1];
      row[j] = x;
    }
    return;
  }
  for (uint32_t i = n / 2; i-- > 0;) SiftDown(row, i, n, less);
  SortHeap(row, n, less);
}

// Appends the points of site s (at squared distance d2 from the query),
// `self` excluded, by ascending external id to out[n..k); returns the new
// count. Where they do not all fit, the smallest ids are kept.
KINETRI_HD inline uint32_t AppendSitePoints(const TriangulationView& v,
                                            uint32_t s, double d2,
                                            uint32_t self, KnnEntry* out,
                                            uint32_t n, uint32_t k) {
  if (v.dup_next[s] == kNoVertex) {
    if (v.ext_of_int[s] != self && n < k) out[n++] = {s, d2};
    return n;
  }
  if (v.site_member_offsets != nullptr) {  // members by ascending id
    const uint32_t end = v.site_member_offsets[s + 1];
    for (uint32_t m = v.site_member_offsets[s]; m < end && n < k; ++m) {
      const uint32_t ext = v.site_members[m];
      if (ext != self) out[n++] = {v.int_of_ext[ext], d2};
    }
    return n;
  }
  // The chain in any order: a bounded insertion by id into out[n0..k).
  const uint32_t n0 = n;
  for (uint32_t p = s; p != kNoVertex; p = v.dup_next[p]) {
    const uint32_t ext = v.ext_of_int[p];
    if (ext == self) continue;
    uint32_t j;
    if (n < k) {
      j = n++;
    } else if (n > n0 && ext < v.ext_of_int[out[n - 1].point]) {
      j = n - 1;
    } else {
      continue;
    }
    while (j > n0 && ext < v.ext_of_int[out[j - 1].point]) {
      out[j] = out[j - 1];
      --j;
    }
    out[j] = {p, d2};
  }
  return n;
}

// KNearestSearch for k <= kKnnBestFirstMax: the sites in the exact order
// from the nearest one (root), each taking the next points of the row,
// as the host executors search with visit marks; here without marks: a
// site is discovered only from its parent (its neighbour that comes first
// from q, popped before it), so each one once. The candidates are the
// best k - (points so far) + 1 sites discovered and not yet taken, enough
// since each site holds at least one point.
KINETRI_HD inline uint32_t KNearestBestFirst(const TriangulationView& v,
                                             const Vec2& q, uint32_t k,
                                             uint32_t root, uint32_t self,
                                             KnnEntry* out) {
  struct Candidate {
    double d2;
    uint32_t site;
  };
  // Live candidates cand[head..size), closest first; at most
  // kKnnBestFirstMax + 2 of them at once (the cap, and one being added).
  constexpr uint32_t kSlots = 2 * (kKnnBestFirstMax + 2);
  Candidate cand[kSlots];
  auto before = [&](const Candidate& a, const Candidate& b) {
    return CompareCloserCached(q, v.pos[a.site], a.d2, v.pos[b.site], b.d2) < 0;
  };
  uint32_t head = 0, size = 0, n = 0;
  cand[size++] = {SquaredDistance(q, v.pos[root]), root};
  while (head < size && n < k) {
    const Candidate c = cand[head++];
    n = AppendSitePoints(v, c.site, c.d2, self, out, n, k);
    if (n >= k) break;
    const uint32_t cap = k - n + 1;
    for (const uint32_t* it = v.RowBegin(c.site); it != v.RowEnd(c.site);
         ++it) {
      const uint32_t w = *it;
      if (w == root) continue;
      const Candidate e{SquaredDistance(q, v.pos[w]), w};
      if (size - head >= cap && !before(e, cand[size - 1])) continue;
      if (FirstNeighbor(v, q, w, /*include_self=*/false) != c.site) continue;
      if (size == kSlots) {  // the live ones to the front
        for (uint32_t i = head; i < size; ++i) cand[i - head] = cand[i];
        size -= head;
        head = 0;
      }
      uint32_t j = size++;
      while (j > head && before(e, cand[j - 1])) {
        cand[j] = cand[j - 1];
        --j;
      }
      cand[j] = e;
      if (size - head > cap) --size;
    }
  }
  return n;
}

// The k first points from q (self excluded) into out[0..k), closest first;
// returns how many were found (< k only when the set is smaller).
KINETRI_HD inline uint32_t KNearestSearch(const TriangulationView& v,
                                          const Vec2& q, uint32_t k,
                                          uint32_t root, uint32_t self,
                                          KnnEntry* out) {
  if (k == 0) return 0;
  if (k <= kKnnBestFirstMax) return KNearestBestFirst(v, q, k, root, self, out);
  // Starting radius: the farthest neighbour of the nearest site.
  double r2 = 0.0;
  for (const uint32_t* it = v.RowBegin(root); it != v.RowEnd(root); ++it) {
    const double d = SquaredDistance(q, v.pos[*it]);
    if (d > r2) r2 = d;
  }
  double r = sqrt(r2);
  if (!(r > 0.0)) r = 1.0;  // a single site: any radius holds it
  // Grow until the disk holds k points or all of them (a disk holding every
  // site stops growing the count).
  uint32_t have = CountPointsWithin(v, q, r, root, self, k);
  const uint32_t total = v.num_points - (self != kNoVertex ? 1u : 0u);
  while (have < k && have < total) {
    r *= 2.0;
    have = CountPointsWithin(v, q, r, root, self, k);
  }
  // Keep the k first (exact order; coincident points by external id) in a
  // bounded max-heap (the last kept entry on top), sorted at the end:
  // O(m log k) for the m points of the disk (one thread per query on a GPU
  // made a k of thousands take seconds by insertion).
  const EntryOrder less{v, q};
  uint32_t n = 0;
  // Adds point p at squared distance d2; false when it does not enter the
  // k first.
  auto insert = [&](uint32_t p, double d2) {
    const KnnEntry x{p, d2};
    if (n == k) {
      if (!less(x, out[0])) return false;
      out[0] = x;
      SiftDown(out, 0, k, less);
      return true;
    }
    uint32_t j = n++;  // sift up
    while (j > 0 && less(out[(j - 1) / 2], x)) {
      out[j] = out[(j - 1) / 2];
      j = (j - 1) / 2;
    }
    out[j] = x;
    return true;
  };
  RadiusSearch(v, q, r, root, [&](uint32_t s) {
    const double d2 = SquaredDistance(q, v.pos[s]);
    if (v.dup_next[s] != kNoVertex && v.site_member_offsets != nullptr) {
      // Members by ascending external id: once one stays out, all the
      // later ones do (same distance, larger id).
      const uint32_t end = v.site_member_offsets[s + 1];
      for (uint32_t m = v.site_member_offsets[s]; m < end; ++m) {
        const uint32_t ext = v.site_members[m];
        if (ext == self) continue;
        if (!insert(v.int_of_ext[ext], d2)) break;
      }
      return;
    }
    for (uint32_t p = s; p != kNoVertex; p = v.dup_next[p]) {
      if (v.ext_of_int[p] != self) insert(p, d2);
    }
  });
  SortHeap(out, n, less);
  return n;
}

}  // namespace kinetri::core

#endif  // KINETRI_CORE_QUERY_SEARCH_H_
