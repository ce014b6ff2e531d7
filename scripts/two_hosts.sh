#!/usr/bin/env bash
# The graph on two "hosts" of one DDS domain: two network namespaces on this machine joined by a
# veth pair (10.231.63.1 <-> 10.231.63.2), as the original system ran on several computers.
#   camera host : bag_player + blob_features_<cam> (images stay on this host)
#   tracker host: skeleton + feedback_projection + body_publisher + bag_recorder
# Blobs, priors and bodies cross the link over UDP (shared memory off: FASTDDS_BUILTIN_TRANSPORTS=UDPv4,
# and not config/fastdds.xml, whose shared-memory transport would bypass the link).
#
# Usage: ROS_DOMAIN_ID=63 bash scripts/two_hosts.sh BAG OUT [key=value ...]   (graph variables, as --set)
#
# Needs CAP_NET_ADMIN (root; on this machine the session is root); exits 77 with one line when
# network namespaces cannot be created. On real machines run the same two `artrack launch --only`
# commands (below) on the two hosts with the same ROS_DOMAIN_ID and ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET.
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
if [ "${1:-}" = "-h" ] || [ "${1:-}" = "--help" ]; then
  sed -n '2,/^[^#]/{/^#/s/^# \{0,1\}//p}' "$0"  # the comment block above
  exit 0
fi
if [ $# -lt 2 ]; then echo "usage: ROS_DOMAIN_ID=N $0 BAG OUT [key=value ...]" >&2; exit 2; fi
BAG=$(realpath "$1"); OUT=$(realpath -m "$2"); shift 2
DOMAIN=${ROS_DOMAIN_ID:-63}
SETS=("$@")
A=artrack_cam_$$; B=artrack_trk_$$; VA=art$$a; VB=art$$b
IP_A=10.231.63.1; IP_B=10.231.63.2

cleanup() { ip netns del "$A" 2>/dev/null || true; ip netns del "$B" 2>/dev/null || true; }
trap cleanup EXIT
if ! err=$(ip netns add "$A" 2>&1); then
  echo "two_hosts: cannot create a network namespace ($err); needs root / CAP_NET_ADMIN" >&2; exit 77
fi
ip netns add "$B"
ip link add "$VA" type veth peer name "$VB"
ip link set "$VA" netns "$A"; ip link set "$VB" netns "$B"
for ns in "$A:$VA:$IP_A" "$B:$VB:$IP_B"; do
  IFS=: read -r n dev ip <<< "$ns"
  ip -n "$n" addr add "$ip/24" dev "$dev"
  ip -n "$n" link set lo up
  ip -n "$n" link set "$dev" up
  ip -n "$n" route add 224.0.0.0/4 dev "$dev"   # DDS discovery multicast over the link
done

mkdir -p "$OUT"
# shellcheck disable=SC1091
. "$ROOT/scripts/env.sh"
COMMON=(env -u FASTRTPS_DEFAULT_PROFILES_FILE ROS_DOMAIN_ID="$DOMAIN" ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET FASTDDS_BUILTIN_TRANSPORTS=UDPv4)
ARGS=(config/graph.yaml --set "bag=$BAG" --set "out=$OUT/graph")
for s in "${SETS[@]}"; do ARGS+=(--set "$s"); done
cd "$ROOT"
echo "two_hosts: tracker host $IP_B: skeleton, feedback_projection, body_publisher, bag_recorder"
ip netns exec "$B" "${COMMON[@]}" ROS_STATIC_PEERS="$IP_A" artrack launch "${ARGS[@]}" \
  --only skeleton --only feedback_projection --only body_publisher --only bag_recorder \
  --log-dir "$OUT/logs_tracker" &
TRACKER=$!
echo "two_hosts: camera host $IP_A: bag_player, blob_features_*"
rc=0
ip netns exec "$A" "${COMMON[@]}" ROS_STATIC_PEERS="$IP_B" artrack launch "${ARGS[@]}" \
  --only 'blob_features_*' --only bag_player --log-dir "$OUT/logs_cameras" || rc=$?
kill -INT "$TRACKER" 2>/dev/null || true
wait "$TRACKER" || true
# bytes that crossed the link (the camera host's side)
ip -n "$A" -s link show "$VA" | awk '/RX:/{getline; rx=$1} /TX:/{getline; tx=$1} END{print "two_hosts: link bytes rx " rx " tx " tx}'
exit "$rc"
