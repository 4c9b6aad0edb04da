// Writes a picture of an exported triangulation (edges, points, NN links).
#ifndef KINETRI_CLIENT_CPP_SVG_WRITER_H_
#define KINETRI_CLIENT_CPP_SVG_WRITER_H_

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "client/cpp/kinetri_client.h"

namespace kinetri {

struct SvgOptions {
  int max_points = 4000;  // zoom into a central window of about this many
  int size_px = 900;
  std::string title = "Kinetri";
};

// nearest: one id per point or empty; highlight: per point or empty.
absl::Status WriteMeshSvg(const Mesh& mesh,
                          const std::vector<uint32_t>& nearest,
                          const std::vector<bool>& highlight,
                          const std::string& path,
                          const SvgOptions& options = {});

}  // namespace kinetri

#endif  // KINETRI_CLIENT_CPP_SVG_WRITER_H_
