// Plain 2D point/vector type shared by every layer of the core.
#ifndef KINETRI_CORE_VEC2_H_
#define KINETRI_CORE_VEC2_H_

#include "core/hd.h"

namespace kinetri::core {

struct Vec2 {
  double x = 0.0;
  double y = 0.0;
};

KINETRI_HD inline bool operator==(const Vec2& a, const Vec2& b) {
  return a.x == b.x && a.y == b.y;
}
KINETRI_HD inline bool operator!=(const Vec2& a, const Vec2& b) {
  return !(a == b);
}
// Lexicographic (x, then y) order, used by the symbolic perturbation.
KINETRI_HD inline bool LexLess(const Vec2& a, const Vec2& b) {
  return a.x < b.x || (a.x == b.x && a.y < b.y);
}

}  // namespace kinetri::core

#endif  // KINETRI_CORE_VEC2_H_
