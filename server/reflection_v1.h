// gRPC server reflection v1 (grpc.reflection.v1.ServerReflection), next to
// the v1alpha service that gRPC 1.51's plugin provides. Answers from the
// descriptors compiled into this binary (the generated pool): tools that
// speak only v1 (newer grpcurl, Postman, grpc-ui) see the same API.
#ifndef KINETRI_SERVER_REFLECTION_V1_H_
#define KINETRI_SERVER_REFLECTION_V1_H_

#include <string>
#include <vector>

#include "grpc/reflection/v1/reflection.grpc.pb.h"

namespace kinetri::server {

class ReflectionV1Service final
    : public grpc::reflection::v1::ServerReflection::Service {
 public:
  // `services`: the full names list_services reports.
  explicit ReflectionV1Service(std::vector<std::string> services);

  grpc::Status ServerReflectionInfo(
      grpc::ServerContext* ctx,
      grpc::ServerReaderWriter<grpc::reflection::v1::ServerReflectionResponse,
                               grpc::reflection::v1::ServerReflectionRequest>*
          stream) override;

 private:
  const std::vector<std::string> services_;
};

}  // namespace kinetri::server

#endif  // KINETRI_SERVER_REFLECTION_V1_H_
