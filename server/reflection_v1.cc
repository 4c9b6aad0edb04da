// gRPC server reflection v1 from the binary's generated descriptor pool.
#include "server/reflection_v1.h"

#include <google/protobuf/descriptor.h>
#include <google/protobuf/descriptor.pb.h>

#include <set>
#include <utility>

namespace kinetri::server {
namespace {

namespace v1 = grpc::reflection::v1;
using google::protobuf::DescriptorPool;
using google::protobuf::FileDescriptor;

void SetError(v1::ServerReflectionResponse* resp, grpc::StatusCode code,
              const std::string& message) {
  resp->mutable_error_response()->set_error_code(static_cast<int32_t>(code));
  resp->mutable_error_response()->set_error_message(message);
}

// `file` and the files it imports, each once per stream (a client that
// already received a file is not sent it again).
void AddFiles(const FileDescriptor* file, std::set<std::string>* sent,
              v1::FileDescriptorResponse* out) {
  if (file == nullptr || !sent->insert(file->name()).second) return;
  google::protobuf::FileDescriptorProto proto;
  file->CopyTo(&proto);
  out->add_file_descriptor_proto(proto.SerializeAsString());
  for (int i = 0; i < file->dependency_count(); ++i) {
    AddFiles(file->dependency(i), sent, out);
  }
}

}  // namespace

ReflectionV1Service::ReflectionV1Service(std::vector<std::string> services)
    : services_(std::move(services)) {}

grpc::Status ReflectionV1Service::ServerReflectionInfo(
    grpc::ServerContext* ctx,
    grpc::ServerReaderWriter<v1::ServerReflectionResponse,
                             v1::ServerReflectionRequest>* stream) {
  const DescriptorPool* pool = DescriptorPool::generated_pool();
  std::set<std::string> sent;
  v1::ServerReflectionRequest req;
  while (stream->Read(&req)) {
    if (ctx->IsCancelled()) {
      return grpc::Status(grpc::StatusCode::CANCELLED, "cancelled");
    }
    v1::ServerReflectionResponse resp;
    resp.set_valid_host(req.host());
    *resp.mutable_original_request() = req;
    switch (req.message_request_case()) {
      case v1::ServerReflectionRequest::kFileByFilename: {
        const FileDescriptor* f = pool->FindFileByName(req.file_by_filename());
        if (f == nullptr) {
          SetError(&resp, grpc::StatusCode::NOT_FOUND,
                   "file not found: " + req.file_by_filename());
        } else {
          AddFiles(f, &sent, resp.mutable_file_descriptor_response());
        }
        break;
      }
      case v1::ServerReflectionRequest::kFileContainingSymbol: {
        const FileDescriptor* f =
            pool->FindFileContainingSymbol(req.file_containing_symbol());
        if (f == nullptr) {
          SetError(&resp, grpc::StatusCode::NOT_FOUND,
                   "symbol not found: " + req.file_containing_symbol());
        } else {
          AddFiles(f, &sent, resp.mutable_file_descriptor_response());
        }
        break;
      }
      case v1::ServerReflectionRequest::kFileContainingExtension: {
        const auto& ext = req.file_containing_extension();
        const google::protobuf::Descriptor* type =
            pool->FindMessageTypeByName(ext.containing_type());
        const google::protobuf::FieldDescriptor* field =
            type == nullptr
                ? nullptr
                : pool->FindExtensionByNumber(type, ext.extension_number());
        if (field == nullptr) {
          SetError(&resp, grpc::StatusCode::NOT_FOUND,
                   "extension not found: " + ext.containing_type() + " " +
                       std::to_string(ext.extension_number()));
        } else {
          AddFiles(field->file(), &sent,
                   resp.mutable_file_descriptor_response());
        }
        break;
      }
      case v1::ServerReflectionRequest::kAllExtensionNumbersOfType: {
        const google::protobuf::Descriptor* type =
            pool->FindMessageTypeByName(req.all_extension_numbers_of_type());
        if (type == nullptr) {
          SetError(&resp, grpc::StatusCode::NOT_FOUND,
                   "type not found: " + req.all_extension_numbers_of_type());
        } else {
          std::vector<const google::protobuf::FieldDescriptor*> exts;
          pool->FindAllExtensions(type, &exts);
          auto* out = resp.mutable_all_extension_numbers_response();
          out->set_base_type_name(type->full_name());
          for (const auto* e : exts) out->add_extension_number(e->number());
        }
        break;
      }
      case v1::ServerReflectionRequest::kListServices:
        for (const std::string& name : services_) {
          resp.mutable_list_services_response()->add_service()->set_name(name);
        }
        break;
      default:
        SetError(&resp, grpc::StatusCode::UNIMPLEMENTED,
                 "unknown reflection request");
        break;
    }
    if (!stream->Write(resp)) break;
  }
  return grpc::Status::OK;
}

}  // namespace kinetri::server
