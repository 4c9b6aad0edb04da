#!/usr/bin/env bash
# Makes development secrets for deploy/compose.yaml in deploy/secrets/
# (git-ignored): a private CA, a server certificate for "localhost" and
# "kinetri", and one bearer token for tenant "dev". Production: use your own
# CA and tokens (docs/SECURITY.md).
#   bash deploy/make_dev_secrets.sh && docker compose -f deploy/compose.yaml up --build
#   kinetri-cli --server=localhost:50051 --ca=deploy/secrets/tls/ca.crt \
#     --token="$(cut -d' ' -f1 deploy/secrets/auth/tokens)" list
set -euo pipefail
out="$(dirname "$0")/secrets"
mkdir -p "$out/tls" "$out/auth"
cd "$out"
q() { "$@" >/dev/null 2>&1; }
q openssl req -x509 -newkey rsa:3072 -nodes -days 365 -subj "/CN=kinetri-dev-ca" \
  -keyout tls/ca.key -out tls/ca.crt
q openssl req -newkey rsa:3072 -nodes -subj "/CN=kinetri" \
  -keyout tls/tls.key -out tls/tls.csr
printf 'subjectAltName=DNS:localhost,DNS:kinetri,IP:127.0.0.1\nextendedKeyUsage=serverAuth\n' \
  >tls/tls.ext
q openssl x509 -req -in tls/tls.csr -CA tls/ca.crt -CAkey tls/ca.key \
  -CAcreateserial -days 365 -extfile tls/tls.ext -out tls/tls.crt
rm -f tls/tls.csr tls/tls.ext tls/ca.srl
printf '%s dev\n' "$(openssl rand -hex 32)" >auth/tokens
# The server runs as uid 10001: it must be able to read them.
chmod 0644 tls/tls.crt tls/ca.crt auth/tokens tls/tls.key
echo "secrets in $out (CA: $out/tls/ca.crt, token: first word of $out/auth/tokens)"
