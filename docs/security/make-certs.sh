#!/bin/sh
# Make a private CA and certificates for a TACF deployment over Zenoh TLS (needs only the openssl command).
#
#   docs/security/make-certs.sh DIR [NAME ...]
#
# DIR gets: ca.pem + ca.key (the CA; keep ca.key offline), service.pem + service.key (the edge box's listen
# certificate, valid for localhost, 127.0.0.1 and every NAME: DNS names or IP addresses that clients use to reach
# the box), and ground.pem/.key, viewer.pem/.key and camera.pem/.key (client certificates with CN ground / viewer /
# camera, only needed with mutual TLS). Keys are EC P-256, certificates are valid for 825 days. Never commit the keys.
set -eu
dir=${1:?usage: make-certs.sh DIR [NAME ...]}
shift
mkdir -p "$dir"
cd "$dir"
umask 077

san="DNS:localhost,IP:127.0.0.1"
for name in "$@"; do
    case $name in
        *:*) san="$san,IP:$name" ;;          # an IPv6 address
        *[!0-9.]*) san="$san,DNS:$name" ;;   # anything else but digits and dots is a host name
        *) san="$san,IP:$name" ;;
    esac
done

openssl ecparam -name prime256v1 -genkey -noout -out ca.key
openssl req -x509 -new -key ca.key -sha256 -days 825 -subj "/CN=tacf-ca" -out ca.pem \
    -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign"

# leaf NAME CN USAGE [SAN]: a key and a certificate signed by the CA (rustls wants v3 extensions and a SAN).
leaf() {
    openssl ecparam -name prime256v1 -genkey -noout -out "$1.key"
    openssl req -new -key "$1.key" -subj "/CN=$2" -out "$1.csr"
    printf 'basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\nextendedKeyUsage=%s\n' "$3" \
        > "$1.ext"
    [ -z "${4:-}" ] || printf 'subjectAltName=%s\n' "$4" >> "$1.ext"
    openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -sha256 -days 825 \
        -extfile "$1.ext" -out "$1.pem" 2>/dev/null
    rm -f "$1.csr" "$1.ext"
}

leaf service tacf-service serverAuth,clientAuth "$san"
leaf ground ground clientAuth "DNS:ground"
leaf viewer viewer clientAuth "DNS:viewer"
leaf camera camera clientAuth "DNS:camera"
rm -f ca.srl
chmod 644 ./*.pem
chmod 600 ./*.key    # umask made new files private; keys of an earlier run may have been opened up since
echo "certificates in $(pwd): ca.pem service.pem ground.pem viewer.pem camera.pem (keys: *.key)"
