#!/usr/bin/env bash
# Makes the TLS material of an ebmpc site with openssl: a CA, the router's certificate and one
# client certificate per host (planner or agent), for mutual TLS through deploy/zenohd.json5.
#
#   deploy/make-certs.sh OUT_DIR ROUTER_HOST [CLIENT_NAME...]
#
# OUT_DIR/ca.pem, ca-key.pem             the site's CA (keep ca-key.pem offline)
# OUT_DIR/router.pem, router-key.pem     for the router; subjectAltName = ROUTER_HOST, the name
#                                        (or IP address) clients put in tls/ROUTER_HOST:7448
# OUT_DIR/<name>.pem, <name>-key.pem     one per client; common name = <name>, which the
#                                        router's access control can match (cert_common_names)
#
# Rerunning with the same OUT_DIR reuses its CA, so new clients can be added later.
# Keys are P-256 ECDSA in PKCS#8; certificates are valid for 825 days (the CA for 10 years).
set -euo pipefail

if [[ $# -lt 2 ]]; then
    sed -n '2,14p' "$0" | sed 's/^# \{0,1\}//' >&2
    exit 2
fi
OUT="$1"
ROUTER_HOST="$2"
shift 2
command -v openssl >/dev/null || { echo "error: openssl not found (apt-get install openssl)" >&2; exit 1; }
mkdir -p "$OUT"
umask 077

key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null; }

if [[ ! -f "$OUT/ca.pem" ]]; then
    key "$OUT/ca-key.pem"
    openssl req -x509 -new -key "$OUT/ca-key.pem" -days 3650 -subj "/CN=ebmpc site CA" \
        -addext "basicConstraints=critical,CA:TRUE" \
        -addext "keyUsage=critical,keyCertSign,cRLSign" \
        -out "$OUT/ca.pem"
fi

# sign NAME EXTENSIONS: NAME.pem and NAME-key.pem, signed by the CA.
sign() {
    local name="$1" extensions="$2"
    key "$OUT/$name-key.pem"
    openssl req -new -key "$OUT/$name-key.pem" -subj "/CN=$name" -out "$OUT/$name.csr"
    openssl x509 -req -in "$OUT/$name.csr" -CA "$OUT/ca.pem" -CAkey "$OUT/ca-key.pem" \
        -CAcreateserial -days 825 -extfile <(printf '%s\n' "$extensions") \
        -out "$OUT/$name.pem" 2>/dev/null
    rm -f "$OUT/$name.csr"
}

if [[ "$ROUTER_HOST" =~ ^[0-9.]+$ || "$ROUTER_HOST" == *:* ]]; then
    router_san="IP:$ROUTER_HOST"
else
    router_san="DNS:$ROUTER_HOST"
fi
sign router "basicConstraints=CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=serverAuth
subjectAltName=$router_san"

for client in "$@"; do
    sign "$client" "basicConstraints=CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=clientAuth
subjectAltName=DNS:$client"
done

# Certificates are public; the keys stay readable by their owner only (umask above).
chmod 644 "$OUT"/*.pem
chmod 600 "$OUT"/*-key.pem
echo "TLS material in $OUT: ca.pem, router.pem (for $ROUTER_HOST)${*:+, and clients: $*}"
