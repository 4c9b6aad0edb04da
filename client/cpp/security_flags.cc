// TLS and token flags of the client binaries (see security_flags.h).
#include "client/cpp/security_flags.h"

#include <string>

#include "absl/flags/flag.h"

ABSL_FLAG(std::string, token, "",
          "bearer token sent with every call (default: $KINETRI_TOKEN)");
ABSL_FLAG(std::string, ca, "",
          "PEM CA bundle; connects with TLS when set (default: $KINETRI_CA)");
ABSL_FLAG(std::string, cert, "",
          "PEM client certificate for mutual TLS (default: $KINETRI_CERT)");
ABSL_FLAG(std::string, key, "",
          "PEM private key of --cert (default: $KINETRI_KEY)");
ABSL_FLAG(std::string, tls_server_name, "",
          "name expected in the server's certificate (default: the host of "
          "--server, or $KINETRI_TLS_SERVER_NAME)");

namespace kinetri {

ClientSecurity SecurityFromFlags() {
  ClientSecurity s = ClientSecurity::FromEnvironment();
  auto pick = [](std::string flag, std::string* field) {
    if (!flag.empty()) *field = std::move(flag);
  };
  pick(absl::GetFlag(FLAGS_token), &s.token);
  pick(absl::GetFlag(FLAGS_ca), &s.ca_file);
  pick(absl::GetFlag(FLAGS_cert), &s.cert_file);
  pick(absl::GetFlag(FLAGS_key), &s.key_file);
  pick(absl::GetFlag(FLAGS_tls_server_name), &s.server_name);
  return s;
}

}  // namespace kinetri
