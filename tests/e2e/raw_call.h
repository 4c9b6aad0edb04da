// Raw gRPC calls for tests: messages sent as given bytes (valid or not).
#ifndef KINETRI_TESTS_E2E_RAW_CALL_H_
#define KINETRI_TESTS_E2E_RAW_CALL_H_

#include <grpcpp/generic/generic_stub.h>
#include <grpcpp/grpcpp.h>

#include <string>
#include <vector>

namespace kinetri::testing {

// Sends `messages` as raw bytes on `method` ("/package.Service/Method", any
// streaming kind), half-closes, reads every response and returns the final
// status (DEADLINE_EXCEEDED when the server does not end the call within
// `deadline_seconds`).
grpc::Status SendRaw(grpc::GenericStub& stub, const std::string& method,
                     const std::vector<std::string>& messages,
                     int deadline_seconds = 20);

}  // namespace kinetri::testing

#endif  // KINETRI_TESTS_E2E_RAW_CALL_H_
