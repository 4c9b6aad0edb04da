// Streaming requests read as bytes and parsed by the handler.
//
// gRPC's typed Read() returns false both at the end of a stream and when a
// message fails to parse, so a stream whose last message is corrupt would
// look complete (a step stream cut at a step boundary ended with OK). The
// streaming handlers are therefore registered over grpc::ByteBuffer
// (KinetriServiceImpl's constructor) and parse each message here with the
// same protobuf parser gRPC uses.
#ifndef KINETRI_SERVER_MESSAGE_READER_H_
#define KINETRI_SERVER_MESSAGE_READER_H_

#include <grpcpp/grpcpp.h>
#include <grpcpp/support/byte_buffer.h>

#include <cstdint>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"

namespace kinetri::server {

// Reads the next message of `stream` (a ServerReader or ServerReaderWriter
// over grpc::ByteBuffer) into *msg: true for a message, false at the end of
// the stream, INVALID_ARGUMENT when its bytes do not parse as a Message.
template <typename Message, typename Stream>
class MessageReader {
 public:
  explicit MessageReader(Stream* stream) : stream_(stream) {}

  absl::StatusOr<bool> Read(Message* msg) {
    grpc::ByteBuffer bytes;
    if (!stream_->Read(&bytes)) return false;
    ++count_;
    const size_t size = bytes.Length();
    if (!grpc::SerializationTraits<Message>::Deserialize(&bytes, msg).ok()) {
      return absl::InvalidArgumentError(absl::StrCat(
          "message ", count_, " of the stream (", size,
          " bytes) is not a valid ", Message::descriptor()->full_name(),
          ": corrupt bytes; nothing of it was applied"));
    }
    return true;
  }

  // Messages read so far (corrupt ones included).
  uint64_t count() const { return count_; }

 private:
  Stream* stream_;
  uint64_t count_ = 0;
};

}  // namespace kinetri::server

#endif  // KINETRI_SERVER_MESSAGE_READER_H_
