#!/usr/bin/env bash
# Makes throw-away certificates for the security tests in DIR (openssl):
#   ca.pem/ca.key            the test CA
#   server.pem/server.key    server certificate (127.0.0.1, localhost,
#                            kinetri: deploy/proxy/haproxy.cfg) by ca
#   client.pem/client.key    client certificate by ca (mutual TLS)
#   other_ca.pem             an unrelated CA
#   other_client.pem/.key    a client certificate by the unrelated CA
#   other_server.pem/.key    a server certificate by the unrelated CA
#                            (certificate rotation)
set -euo pipefail
dir=${1:?usage: make_test_certs.sh DIR}
mkdir -p "$dir"
cd "$dir"
q() { "$@" >/dev/null 2>&1; }
ca() {  # name
  q openssl req -x509 -newkey rsa:2048 -nodes -days 2 -subj "/CN=$1" \
    -keyout "$1.key" -out "$1.pem"
}
leaf() {  # name ca extensions
  q openssl req -newkey rsa:2048 -nodes -subj "/CN=$1" -keyout "$1.key" \
    -out "$1.csr"
  printf '%s\n' "$3" >"$1.ext"
  q openssl x509 -req -in "$1.csr" -CA "$2.pem" -CAkey "$2.key" \
    -CAcreateserial -days 2 -extfile "$1.ext" -out "$1.pem"
  rm -f "$1.csr" "$1.ext"
}
ca ca
ca other_ca
leaf server ca "subjectAltName=IP:127.0.0.1,DNS:localhost,DNS:kinetri
extendedKeyUsage=serverAuth"
leaf client ca "extendedKeyUsage=clientAuth"
leaf other_client other_ca "extendedKeyUsage=clientAuth"
leaf other_server other_ca "subjectAltName=IP:127.0.0.1,DNS:localhost
extendedKeyUsage=serverAuth"
