#!/bin/sh
# Certificates for a room whose hosts talk over zenoh TLS (see README.md here).
#
#   deploy/tls/make_certs.sh DIR HOST [NAME_OR_IP ...]
#
# Makes DIR/ca.pem and DIR/ca.key (the room's certificate authority) unless they exist,
# then DIR/HOST.pem and DIR/HOST.key: HOST's certificate, signed by that CA, valid as a
# server and as a client (mutual TLS), for the names HOST, localhost, 127.0.0.1 and every
# further NAME_OR_IP given (the names other hosts use to reach it). Keep ca.key off the
# hosts: it only signs.
set -eu
[ $# -ge 2 ] || { echo "usage: $0 DIR HOST [NAME_OR_IP ...]" >&2; exit 2; }
dir=$1; host=$2; shift 2
mkdir -p "$dir"
cd "$dir"
curve="-newkey ec -pkeyopt ec_paramgen_curve:prime256v1"
if [ ! -f ca.pem ]; then
  openssl req -x509 $curve -nodes -days 3650 -subj "/CN=smartroom room CA" \
    -keyout ca.key -out ca.pem 2>/dev/null
fi
san="DNS:$host,DNS:localhost,IP:127.0.0.1"
for name in "$@"; do
  case $name in
    *:*) san="$san,IP:$name";;          # IPv6
    *[!0-9.]*) san="$san,DNS:$name";;   # a host name
    *) san="$san,IP:$name";;            # IPv4
  esac
done
openssl req $curve -nodes -subj "/CN=$host" -keyout "$host.key" -out "$host.csr" 2>/dev/null
printf 'subjectAltName=%s\nbasicConstraints=CA:FALSE\nkeyUsage=digitalSignature\nextendedKeyUsage=serverAuth,clientAuth\n' \
  "$san" > "$host.ext"
openssl x509 -req -in "$host.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -days 825 \
  -extfile "$host.ext" -out "$host.pem" 2>/dev/null
rm -f "$host.csr" "$host.ext"
chmod 600 "$host.key" ca.key
echo "$dir/$host.pem $dir/$host.key (CA $dir/ca.pem)"
