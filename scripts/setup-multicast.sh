#!/usr/bin/env bash
# Route the cell's udp_multicast groups (239.74.163.0/24: the default group 239.74.163.2 and
# the private groups the tests use) over the loopback interface, so that the simulator, the
# runtime and python-can's player and logger talk on this machine only.
# Without it, multicast leaves through the default interface with TTL 1 (python-can's
# normal behaviour), which is what you want only when the cell spans several hosts.
# Needs root. --if-root: do nothing (quietly) when not root or when `ip` is missing.
set -euo pipefail
GROUPS_NET=239.74.163.0/24
if [ "$(id -u)" != 0 ] || ! command -v ip >/dev/null; then
    [ "${1:-}" = "--if-root" ] && exit 0
    echo "setup-multicast.sh: needs root and iproute2 (ip)" >&2
    exit 1
fi
if ip route get 239.74.163.2 2>/dev/null | grep -q " dev lo " \
        && ip route get 239.74.163.100 2>/dev/null | grep -q " dev lo "; then
    exit 0
fi
ip route replace "$GROUPS_NET" dev lo
echo "setup-multicast.sh: $GROUPS_NET now routed over lo" >&2
