// Writes a picture of a triangulation (edges, points, NN links) as SVG.
#include "client/svg_writer.h"

#include <algorithm>
#include <cmath>
#include <fstream>

#include "absl/strings/str_cat.h"

namespace kinetri::client {

absl::Status WriteTriangulationSvg(const core::Triangulation& t,
                                   const core::NeighborLists& nearest,
                                   const std::string& path,
                                   const SvgOptions& options) {
  const std::vector<core::Vec2> pts = t.Positions();
  if (pts.empty()) return absl::InvalidArgumentError("no points to draw");
  core::Vec2 lo = pts[0], hi = pts[0];
  for (const auto& p : pts) {
    lo = {std::min(lo.x, p.x), std::min(lo.y, p.y)};
    hi = {std::max(hi.x, p.x), std::max(hi.y, p.y)};
  }
  // Zoom into the centre so that about max_points points are visible.
  const double frac =
      std::min(1.0, std::sqrt(double(options.max_points) / pts.size()));
  const core::Vec2 c{(lo.x + hi.x) / 2, (lo.y + hi.y) / 2};
  const double half = std::max(hi.x - lo.x, hi.y - lo.y) * frac / 2 + 1e-300;
  const core::Vec2 wlo{c.x - half, c.y - half}, whi{c.x + half, c.y + half};
  auto inside = [&](const core::Vec2& p) {
    return p.x >= wlo.x && p.x <= whi.x && p.y >= wlo.y && p.y <= whi.y;
  };
  const double s = options.size_px / (2 * half);
  auto X = [&](double x) { return (x - wlo.x) * s; };
  auto Y = [&](double y) { return options.size_px - (y - wlo.y) * s; };

  std::ofstream out(path);
  if (!out) return absl::UnavailableError(absl::StrCat("cannot write ", path));
  out << "<svg xmlns='http://www.w3.org/2000/svg' width='" << options.size_px
      << "' height='" << options.size_px << "' viewBox='0 0 " << options.size_px
      << " " << options.size_px << "'>\n"
      << "<rect width='100%' height='100%' fill='white'/>\n"
      << "<g stroke='#3a6ea5' stroke-width='0.6' fill='none'>\n";
  for (const auto& [a, b] : t.Edges()) {
    const auto& p = pts[a];
    const auto& q = pts[b];
    if (!inside(p) && !inside(q)) continue;
    out << "<line x1='" << X(p.x) << "' y1='" << Y(p.y) << "' x2='" << X(q.x)
        << "' y2='" << Y(q.y) << "'/>\n";
  }
  out << "</g>\n<g stroke='#d62728' stroke-width='1.4'>\n";
  for (size_t i = 0; i < nearest.num_queries() && i < pts.size(); ++i) {
    if (nearest.row_size(i) == 0 || !inside(pts[i])) continue;
    const auto& q = pts[nearest.ids[nearest.offsets[i]]];
    out << "<line x1='" << X(pts[i].x) << "' y1='" << Y(pts[i].y) << "' x2='"
        << X(q.x) << "' y2='" << Y(q.y) << "'/>\n";
  }
  out << "</g>\n<g fill='black'>\n";
  for (const auto& p : pts) {
    if (!inside(p)) continue;
    out << "<circle cx='" << X(p.x) << "' cy='" << Y(p.y) << "' r='1.6'/>\n";
  }
  out << "</g>\n<text x='8' y='18' font-family='sans-serif' font-size='13'>"
      << "Kinetri: Delaunay triangulation (blue), nearest neighbour (red), "
      << pts.size() << " points" << (frac < 1 ? " (zoomed window)" : "")
      << "</text>\n</svg>\n";
  if (!out) return absl::DataLossError(absl::StrCat("write failed: ", path));
  return absl::OkStatus();
}

}  // namespace kinetri::client
