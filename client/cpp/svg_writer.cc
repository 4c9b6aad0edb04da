// Writes a picture of an exported triangulation (edges, points, NN links).
#include "client/cpp/svg_writer.h"

#include <algorithm>
#include <cmath>
#include <fstream>

#include "absl/strings/str_cat.h"

namespace kinetri {

absl::Status WriteMeshSvg(const Mesh& mesh,
                          const std::vector<uint32_t>& nearest,
                          const std::vector<bool>& highlight,
                          const std::string& path, const SvgOptions& options) {
  const size_t n = mesh.xy.size() / 2;
  if (n == 0) return absl::InvalidArgumentError("no points to draw");
  auto X0 = [&](size_t i) { return mesh.xy[2 * i]; };
  auto Y0 = [&](size_t i) { return mesh.xy[2 * i + 1]; };
  double lx = X0(0), hx = X0(0), ly = Y0(0), hy = Y0(0);
  for (size_t i = 0; i < n; ++i) {
    lx = std::min(lx, X0(i));
    hx = std::max(hx, X0(i));
    ly = std::min(ly, Y0(i));
    hy = std::max(hy, Y0(i));
  }
  const double frac = std::min(1.0, std::sqrt(double(options.max_points) / n));
  const double cx = (lx + hx) / 2, cy = (ly + hy) / 2;
  const double half = std::max(hx - lx, hy - ly) * frac / 2 * 1.02 + 1e-300;
  auto inside = [&](size_t i) {
    return std::fabs(X0(i) - cx) <= half && std::fabs(Y0(i) - cy) <= half;
  };
  const double s = options.size_px / (2 * half);
  auto X = [&](size_t i) { return (X0(i) - (cx - half)) * s; };
  auto Y = [&](size_t i) {
    return options.size_px - (Y0(i) - (cy - half)) * s;
  };
  std::ofstream out(path);
  if (!out) return absl::UnavailableError(absl::StrCat("cannot write ", path));
  out << "<svg xmlns='http://www.w3.org/2000/svg' width='" << options.size_px
      << "' height='" << options.size_px << "'>\n"
      << "<rect width='100%' height='100%' fill='white'/>\n"
      << "<g stroke='#3a6ea5' stroke-width='0.6' fill='none'>\n";
  for (size_t t = 0; t + 2 < mesh.triangles.size(); t += 3) {
    for (int k = 0; k < 3; ++k) {
      const uint32_t a = mesh.triangles[t + k];
      const uint32_t b = mesh.triangles[t + (k + 1) % 3];
      if (!inside(a) && !inside(b)) continue;
      out << "<line x1='" << X(a) << "' y1='" << Y(a) << "' x2='" << X(b)
          << "' y2='" << Y(b) << "'/>\n";
    }
  }
  out << "</g>\n<g stroke='#d62728' stroke-width='1.3'>\n";
  for (size_t i = 0; i < nearest.size() && i < n; ++i) {
    const uint32_t j = nearest[i];
    if (j >= n || !inside(i)) continue;
    out << "<line x1='" << X(i) << "' y1='" << Y(i) << "' x2='" << X(j)
        << "' y2='" << Y(j) << "'/>\n";
  }
  out << "</g>\n";
  for (size_t i = 0; i < n; ++i) {
    if (!inside(i)) continue;
    const bool hl = i < highlight.size() && highlight[i];
    out << "<circle cx='" << X(i) << "' cy='" << Y(i) << "' r='"
        << (hl ? 2.4 : 1.5) << "' fill='" << (hl ? "#e6550d" : "black")
        << "'/>\n";
  }
  out << "<text x='8' y='18' font-family='sans-serif' font-size='13'>"
      << options.title << " - step " << mesh.step << ", " << n << " points"
      << (frac < 1 ? " (central window)" : "")
      << "; blue: Delaunay edges, red: nearest neighbour</text>\n</svg>\n";
  if (!out) return absl::DataLossError(absl::StrCat("write failed: ", path));
  return absl::OkStatus();
}

}  // namespace kinetri
