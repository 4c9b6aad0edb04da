// Hull checks shared by the CPU executors.
#ifndef KINETRI_CORE_HULL_H_
#define KINETRI_CORE_HULL_H_

#include <cstdint>
#include <vector>

#include "core/mesh.h"
#include "core/vec2.h"

namespace kinetri::core {

// Does the hull polygon wind exactly once (one topmost vertex, walking the
// ghost triangles around the infinite vertex)? Starts from a remembered
// ghost triangle (updated), scanning the mesh only if it is no longer one.
bool HullWindsOnceFrom(const Mesh& mesh, const std::vector<Vec2>& pos,
                       uint32_t* ghost_hint);

}  // namespace kinetri::core

#endif  // KINETRI_CORE_HULL_H_
