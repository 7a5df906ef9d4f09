#!/usr/bin/env bash
# Generates a certificate authority and certificates for a deployment's TLS
# links: the router's server certificate and one client certificate per
# mutually authenticated role (mTLS). The common name of each client
# certificate is the role, which the router's ACL matches
# (`cert_common_names`). For tests and trials; a real site keeps its CA key
# offline and issues certificates with its own tooling.
#
# Usage: deploy/certs/generate.sh OUT_DIR [ROUTER_SAN]
#   ROUTER_SAN: subjectAltName of the router certificate
#   (default: DNS:localhost plus 127.0.0.1-127.0.0.9).
# Writes OUT_DIR/{ca,router,env_controller,sim_controller,robot_agent,tracker_agent,sim_twin,operator,lab_web}.{pem,key},
# and the site's seal keys (runtime/src/seal.rs), kept if present:
#   OUT_DIR/command.seal  for env_controller (real site) and robot_agent (--command-key)
#   OUT_DIR/tracker.seal  for tracker_agent, env_controller and robot_agent (--tracker-key)
set -euo pipefail
out=${1:?usage: generate.sh OUT_DIR [ROUTER_SAN]}
router_san=${2:-DNS:localhost,$(printf 'IP:127.0.0.%d,' 1 2 3 4 5 6 7 8 9 | sed 's/,$//')}
days=${CERT_DAYS:-30}
mkdir -p "$out"
cd "$out"

key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1.key" 2>/dev/null; }

key ca
openssl req -x509 -new -key ca.key -out ca.pem -days "$days" -subj "/CN=offworld-gym-ca" \
    -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign"

# issue NAME SAN EXTENDED_KEY_USAGE
issue() {
    key "$1"
    openssl req -new -key "$1.key" -out "$1.csr" -subj "/CN=$1"
    printf 'basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\nextendedKeyUsage=%s\nsubjectAltName=%s\n' \
        "$3" "$2" >"$1.ext"
    openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -out "$1.pem" \
        -days "$days" -extfile "$1.ext" 2>/dev/null
    rm -f "$1.csr" "$1.ext"
}

issue router "$router_san" serverAuth,clientAuth
for role in env_controller sim_controller robot_agent tracker_agent sim_twin operator lab_web; do
    issue "$role" "DNS:$role" clientAuth
done
rm -f ca.srl
for seal in command tracker; do
    [ -e "$seal.seal" ] || (umask 077 && openssl rand -hex 32 >"$seal.seal")
done
chmod 600 ./*.key ./*.seal
echo "certificates in $(pwd)" >&2
