// Writes a picture of a triangulation (edges, points, NN links) as SVG.
#ifndef KINETRI_CLIENT_SVG_WRITER_H_
#define KINETRI_CLIENT_SVG_WRITER_H_

#include <string>

#include "absl/status/status.h"
#include "core/queries.h"
#include "core/triangulation.h"

namespace kinetri::client {

struct SvgOptions {
  int max_points = 4000;  // zoom into a window holding about this many
  int size_px = 900;
};

// Draws the Delaunay edges and points inside a window (the whole set when
// small), and each point's nearest-neighbour link in red.
absl::Status WriteTriangulationSvg(const core::Triangulation& t,
                                   const core::NeighborLists& nearest,
                                   const std::string& path,
                                   const SvgOptions& options = {});

}  // namespace kinetri::client

#endif  // KINETRI_CLIENT_SVG_WRITER_H_
