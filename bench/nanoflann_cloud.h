// nanoflann adaptor over a vector of Vec2, shared by the benchmarks.
#ifndef KINETRI_BENCH_NANOFLANN_CLOUD_H_
#define KINETRI_BENCH_NANOFLANN_CLOUD_H_

#include <cstdint>
#include <nanoflann.hpp>
#include <vector>

#include "core/vec2.h"

namespace kinetri::bench {

struct NanoCloud {
  const std::vector<core::Vec2>* pts;
  size_t kdtree_get_point_count() const { return pts->size(); }
  double kdtree_get_pt(size_t i, size_t d) const {
    return d == 0 ? (*pts)[i].x : (*pts)[i].y;
  }
  template <class BBox>
  bool kdtree_get_bbox(BBox&) const {
    return false;
  }
};

using NanoTree = nanoflann::KDTreeSingleIndexAdaptor<
    nanoflann::L2_Simple_Adaptor<double, NanoCloud>, NanoCloud, 2, uint32_t>;

}  // namespace kinetri::bench

#endif  // KINETRI_BENCH_NANOFLANN_CLOUD_H_
