# Install rules: binaries, headers (under include/kinetri/, the same layout
# as the source tree, so `#include "core/triangulation.h"` and
# `#include "client/cpp/kinetri_client.h"` work unchanged) and the exported
# targets behind find_package(Kinetri).
include(CMakePackageConfigHelpers)

set(KINETRI_CMAKE_DIR ${CMAKE_INSTALL_LIBDIR}/cmake/Kinetri)
set(KINETRI_EXPORTED kinetri_core)

install(DIRECTORY ${PROJECT_SOURCE_DIR}/core/
  DESTINATION ${CMAKE_INSTALL_INCLUDEDIR}/kinetri/core
  FILES_MATCHING PATTERN "*.h" PATTERN "*.inl")

if(KINETRI_BUILD_SERVICE)
  list(APPEND KINETRI_EXPORTED kinetri_proto kinetri_client)
  install(FILES ${PROJECT_SOURCE_DIR}/client/cpp/kinetri_client.h
                ${PROJECT_SOURCE_DIR}/client/cpp/svg_writer.h
    DESTINATION ${CMAKE_INSTALL_INCLUDEDIR}/kinetri/client/cpp)
  install(FILES ${PROJECT_BINARY_DIR}/proto/kinetri/v1/kinetri.pb.h
                ${PROJECT_BINARY_DIR}/proto/kinetri/v1/kinetri.grpc.pb.h
                ${PROJECT_SOURCE_DIR}/proto/kinetri/v1/kinetri.proto
    DESTINATION ${CMAKE_INSTALL_INCLUDEDIR}/kinetri/kinetri/v1)
  install(TARGETS kinetri-server kinetri-cli kinetri-sim
    RUNTIME DESTINATION ${CMAKE_INSTALL_BINDIR})
endif()

install(TARGETS ${KINETRI_EXPORTED} EXPORT KinetriTargets
  ARCHIVE DESTINATION ${CMAKE_INSTALL_LIBDIR}
  LIBRARY DESTINATION ${CMAKE_INSTALL_LIBDIR}
  INCLUDES DESTINATION ${CMAKE_INSTALL_INCLUDEDIR}/kinetri)
install(EXPORT KinetriTargets NAMESPACE kinetri::
  DESTINATION ${KINETRI_CMAKE_DIR})

set(KINETRI_CONFIG_WITH_SERVICE ${KINETRI_BUILD_SERVICE})
configure_package_config_file(${PROJECT_SOURCE_DIR}/deploy/cmake/KinetriConfig.cmake.in
  ${PROJECT_BINARY_DIR}/KinetriConfig.cmake
  INSTALL_DESTINATION ${KINETRI_CMAKE_DIR})
write_basic_package_version_file(${PROJECT_BINARY_DIR}/KinetriConfigVersion.cmake
  VERSION ${PROJECT_VERSION} COMPATIBILITY SameMinorVersion)
install(FILES ${PROJECT_BINARY_DIR}/KinetriConfig.cmake
              ${PROJECT_BINARY_DIR}/KinetriConfigVersion.cmake
  DESTINATION ${KINETRI_CMAKE_DIR})
