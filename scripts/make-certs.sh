#!/usr/bin/env bash
# Make a CA and one certificate per drivebench identity for a secure stack (docs/security.md).
#   bash scripts/make-certs.sh DIR [ROUTER_NAMES]
# DIR gets ca.pem (give it to every machine), ca.key (keep it off the machines), and NAME.pem + NAME.key for the
# router and for each identity of deploy/secure/router.yaml. ROUTER_NAMES are the names the processes use to reach
# the router, as subjectAltName entries (default: DNS:localhost,IP:127.0.0.1; add e.g. DNS:router.lan,IP:10.0.0.5).
# Existing files are kept: run it again after adding names to make only the missing certificates.
set -euo pipefail
dir=${1:?usage: make-certs.sh DIR [ROUTER_NAMES]}
router_names=${2:-DNS:localhost,IP:127.0.0.1}
mkdir -p "$dir"
cd "$dir"
if [ ! -f ca.pem ]; then
  openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -keyout ca.key -out ca.pem -days 3650 \
    -subj "/CN=drivebench CA" -addext "basicConstraints=critical,CA:TRUE" \
    -addext "keyUsage=critical,keyCertSign,cRLSign" 2>/dev/null
fi
cert() {  # cert NAME SUBJECT_ALT_NAMES: NAME.pem and NAME.key, common name NAME, signed by the CA
  [ -f "$1.pem" ] && return 0
  openssl req -new -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -keyout "$1.key" -out "$1.csr" \
    -subj "/CN=$1" 2>/dev/null
  printf 'basicConstraints=CA:FALSE\nextendedKeyUsage=serverAuth,clientAuth\nsubjectAltName=%s\n' "$2" > "$1.ext"
  openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -days 825 -sha256 -extfile "$1.ext" \
    -out "$1.pem" 2>/dev/null
  rm -f "$1.csr" "$1.ext"
}
cert router "$router_names"
for name in sim noise scorer recorder viz brain orchestrator viewer; do cert "$name" "DNS:$name"; done
chmod 600 ./*.key
echo "certificates in $dir: ca.pem, router, sim, noise, scorer, recorder, viz, brain, orchestrator, viewer" >&2
