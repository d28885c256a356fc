#!/usr/bin/env bash
# Install the headless browser the dashboard tests drive: Debian's chromium and chromium-driver.
# Usage: setup-browser.sh            install when /usr/bin/chromium is missing (needs root + apt-get)
#        setup-browser.sh --if-root  the same, but quietly do nothing when not root
# Playwright drives this system browser (executable_path=/usr/bin/chromium); `playwright install`
# is never used: it downloads a browser build of its own.
set -uo pipefail
if [ -x /usr/bin/chromium ]; then
    exit 0
fi
if [ "$(id -u)" != 0 ]; then
    [ "${1:-}" = "--if-root" ] && exit 0
    echo "setup-browser.sh: chromium is missing and installing it needs root (apt-get install chromium chromium-driver)" >&2
    exit 1
fi
if ! command -v apt-get >/dev/null; then
    echo "setup-browser.sh: chromium is missing and there is no apt-get here; the browser tests will skip" >&2
    exit 1
fi
echo "testcell: installing chromium and chromium-driver with apt-get" >&2
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq >/dev/null || { echo "setup-browser.sh: apt-get update failed" >&2; exit 1; }
apt-get install -y -qq --no-install-recommends chromium chromium-driver fonts-dejavu-core >/dev/null \
    || { echo "setup-browser.sh: apt-get install chromium chromium-driver failed" >&2; exit 1; }
/usr/bin/chromium --version >&2
