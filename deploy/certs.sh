#!/usr/bin/env bash
# deploy/certs.sh OUT_DIR PRINCIPAL[=ADDRESS[,ADDRESS...]] ...
#
# Makes the swarm's certificate authority (once: an existing OUT_DIR/ca.pem is reused) and one
# key + certificate per principal, signed by it, for zenoh's mutual TLS:
#   - CN = the principal's name, which the router's access control matches
#     (`cert_common_names` in deploy/zenoh/router.json5): `router`, `ground`, `world`, and one
#     per drone, named as the drone (`alfa`, `bravo`, ...);
#   - subjectAltName = its addresses (IP or DNS name; the router's must be the address the
#     others connect to, since they verify it);
#   - keys are created mode 0600 and, with TACOS_CERT_OWNER=user[:group], given to that user
#     (the services' own, `tacos` in deploy/systemd), so only the service can read them.
# Output per principal: OUT_DIR/<name>.pem (certificate) and OUT_DIR/<name>-key.pem.
# Example:
#   deploy/certs.sh /etc/tacos/certs router=10.0.0.1,tacos-router ground=10.0.0.2 \
#       world=10.0.0.3 alfa=10.0.1.1 bravo=10.0.1.2
# Keys are EC P-256; certificates last TACOS_CERT_DAYS days (default 825).
set -euo pipefail

if [ $# -lt 2 ]; then
	sed -n '2,19p' "$0" | sed 's/^# \{0,1\}//' >&2
	exit 2
fi
out=$1
shift
days=${TACOS_CERT_DAYS:-825}
owner=${TACOS_CERT_OWNER:-}
mkdir -p "$out"
umask 077

if [ ! -f "$out/ca.pem" ]; then
	openssl ecparam -name prime256v1 -genkey -noout -out "$out/ca-key.pem"
	openssl req -x509 -new -key "$out/ca-key.pem" -sha256 -days "$days" \
		-subj "/CN=tacos-swarm-ca" -out "$out/ca.pem" 2>/dev/null
	chmod 0644 "$out/ca.pem"
	echo "made the CA: $out/ca.pem (keep $out/ca-key.pem offline once every certificate is made)"
fi

for spec in "$@"; do
	name=${spec%%=*}
	addresses=
	[ "$spec" != "$name" ] && addresses=${spec#*=}
	if ! [[ "$name" =~ ^[a-z0-9][a-z0-9_-]*$ ]]; then
		echo "error: '$name' is not a principal name (lower-case letters, digits, - and _)" >&2
		exit 2
	fi
	san=
	IFS=',' read -r -a list <<<"$addresses"
	for a in "${list[@]}"; do
		[ -z "$a" ] && continue
		if [[ "$a" =~ ^[0-9.]+$ || "$a" == *:* ]]; then san+="IP:$a,"; else san+="DNS:$a,"; fi
	done
	san+="DNS:$name"
	ext=$(mktemp)
	trap 'rm -f "$ext"' EXIT
	printf 'subjectAltName=%s\nbasicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\nextendedKeyUsage=serverAuth,clientAuth\n' "$san" >"$ext"
	openssl ecparam -name prime256v1 -genkey -noout -out "$out/$name-key.pem"
	openssl req -new -key "$out/$name-key.pem" -subj "/CN=$name" -out "$out/$name.csr" 2>/dev/null
	openssl x509 -req -in "$out/$name.csr" -CA "$out/ca.pem" -CAkey "$out/ca-key.pem" \
		-CAcreateserial -days "$days" -sha256 -extfile "$ext" -out "$out/$name.pem" 2>/dev/null
	rm -f "$out/$name.csr" "$ext"
	chmod 0600 "$out/$name-key.pem"
	chmod 0644 "$out/$name.pem"
	[ -n "$owner" ] && chown "$owner" "$out/$name-key.pem"
	echo "made $name: $out/$name.pem ($san)"
done
