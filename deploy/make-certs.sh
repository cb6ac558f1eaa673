#!/usr/bin/env bash
# Make a private CA and one certificate per splittag identity, for Zenoh TLS with mutual
# authentication (deploy/secure.toml). The common name (CN) of each certificate is the identity the
# routers' access control matches: edge, robot, camera, slam, controller, operator.
#
#   deploy/make-certs.sh [OUT_DIR] [EXTRA_SAN ...]
#   SPLITTAG_CERT_NAMES="slam edge1 robot1 robot1-camera operator" deploy/make-certs.sh certs   # other names
#
# (`splittag fleet --config F --make-certs` issues a fleet's names, one per process: see docs/fleet.md.)
# OUT_DIR defaults to certs/. Every certificate is valid for localhost and 127.0.0.1 (the edge's also
# for the emulated link's edge addresses, 10.77.0.2 and 10.78.0.2: `splittag up --link`) plus each
# EXTRA_SAN (an IP address or a DNS name: the edge's and the robot's addresses when robot and edge
# are two hosts; slam reaches the robot's router too, as its second endpoint).
# Keep ca.key offline after use: whoever holds it can mint identities.
set -euo pipefail

out=${1:-certs}
shift || true
read -r -a identities <<< "${SPLITTAG_CERT_NAMES:-edge robot camera slam controller operator}"
for id in "${identities[@]}"; do
  [[ $id =~ ^[A-Za-z0-9_.-]+$ ]] || { echo "make-certs: $id is not a certificate name (letters, digits, _ . -)" >&2; exit 2; }
done
days=${SPLITTAG_CERT_DAYS:-825}

mkdir -p "$out"
umask 077
san="DNS:localhost,IP:127.0.0.1"
# the edge's certificate also names the emulated link's addresses of the edge (`splittag up --config
# deploy/secure.toml --link 5g`: the robot dials it at 10.77.0.2 across the shaped link, the tools at
# 10.78.0.2); no other identity is dialled there
link_san="IP:10.77.0.2,IP:10.78.0.2"
for extra in "$@"; do
  if [[ $extra =~ ^[0-9.]+$ || $extra == *:* ]]; then san+=",IP:$extra"; else san+=",DNS:$extra"; fi
done

if [[ ! -f $out/ca.pem ]]; then
  openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -days "$days" \
    -subj "/CN=splittag-ca" -keyout "$out/ca.key" -out "$out/ca.pem" 2>/dev/null
fi

for id in "${identities[@]}"; do
  openssl req -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -subj "/CN=$id" \
    -keyout "$out/$id.key" -out "$out/$id.csr" 2>/dev/null
  names=$san
  if [[ $id == edge ]]; then names+=",$link_san"; fi
  printf 'subjectAltName=%s\nextendedKeyUsage=serverAuth,clientAuth\nbasicConstraints=CA:FALSE\n' "$names" > "$out/$id.ext"
  openssl x509 -req -in "$out/$id.csr" -CA "$out/ca.pem" -CAkey "$out/ca.key" -CAcreateserial \
    -days "$days" -extfile "$out/$id.ext" -out "$out/$id.pem" 2>/dev/null
  rm -f "$out/$id.csr" "$out/$id.ext"
done
chmod 644 "$out"/*.pem
echo "certificates for ${identities[*]} in $out/ (CA: $out/ca.pem; SAN $san; the edge's also $link_san)"
