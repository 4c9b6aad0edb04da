// RETURN_IF_ERROR / ASSIGN_OR_RETURN (Abseil 20220623 ships neither).
#ifndef KINETRI_CORE_STATUS_MACROS_H_
#define KINETRI_CORE_STATUS_MACROS_H_

#include "absl/status/status.h"
#include "absl/status/statusor.h"

#define KINETRI_CONCAT_INNER_(a, b) a##b
#define KINETRI_CONCAT_(a, b) KINETRI_CONCAT_INNER_(a, b)

#define RETURN_IF_ERROR(expr)                          \
  do {                                                 \
    const ::absl::Status kinetri_status_ = (expr);     \
    if (!kinetri_status_.ok()) return kinetri_status_; \
  } while (0)

#define ASSIGN_OR_RETURN(lhs, expr)                                         \
  KINETRI_ASSIGN_OR_RETURN_IMPL_(KINETRI_CONCAT_(statusor_, __LINE__), lhs, \
                                 expr)

#define KINETRI_ASSIGN_OR_RETURN_IMPL_(tmp, lhs, expr) \
  auto tmp = (expr);                                   \
  if (!tmp.ok()) return tmp.status();                  \
  lhs = std::move(tmp).value()

#endif  // KINETRI_CORE_STATUS_MACROS_H_
