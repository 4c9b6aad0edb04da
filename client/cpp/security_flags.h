// Flags shared by kinetri-cli and kinetri-sim for TLS and tokens: --token,
// --ca, --cert, --key, --tls_server_name; each falls back to its
// environment variable (KINETRI_TOKEN, KINETRI_CA, KINETRI_CERT,
// KINETRI_KEY, KINETRI_TLS_SERVER_NAME) when not given.
#ifndef KINETRI_CLIENT_CPP_SECURITY_FLAGS_H_
#define KINETRI_CLIENT_CPP_SECURITY_FLAGS_H_

#include "client/cpp/kinetri_client.h"

namespace kinetri {

ClientSecurity SecurityFromFlags();

}  // namespace kinetri

#endif  // KINETRI_CLIENT_CPP_SECURITY_FLAGS_H_
