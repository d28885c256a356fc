#!/usr/bin/env bash
# Create and bring up the virtual SocketCAN interface vcan0 (needs root and the vcan module).
# After this, `testcell up` (bus auto) uses socketcan on vcan0, and can-utils work:
#   candump -L vcan0            canplayer -I file.log vcan0=can0
set -euo pipefail
IFACE="${1:-vcan0}"
if [ "$(id -u)" != 0 ]; then
    echo "setup-vcan.sh: run as root (sudo scripts/setup-vcan.sh)" >&2
    exit 1
fi
if ! modprobe vcan 2>/dev/null && ! [ -d /sys/module/vcan ]; then
    echo "setup-vcan.sh: the kernel has no vcan module; use --bus udp_multicast instead" >&2
    exit 1
fi
ip link show "$IFACE" >/dev/null 2>&1 || ip link add dev "$IFACE" type vcan
ip link set up "$IFACE"
echo "setup-vcan.sh: $IFACE is up"
