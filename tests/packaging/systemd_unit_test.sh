#!/bin/sh
# systemd_unit: deploy/systemd/kdrt.service.in (as configured for the build tree) passes
# `systemd-analyze verify` without a single message, and holds the settings a daemon install
# needs: readiness by sd_notify, a dynamic user with the store as its state directory, the
# hardening, and a stop timeout longer than the config's shutdown_timeout_s.
#   systemd_unit_test.sh UNIT CONFIG_JSON
set -eu
unit=$1
config=$2
fail() { echo "systemd_unit: $*" >&2; exit 1; }
[ -f "$unit" ] || fail "no unit at $unit (configure the build)"
# systemd-analyze wants the unit's own name; it also checks that ExecStart's program exists.
out=$(systemd-analyze verify "$unit" 2>&1) || fail "systemd-analyze verify failed:
$out"
[ -z "$out" ] || fail "systemd-analyze verify printed:
$out"
for setting in Type=notify NotifyAccess=main DynamicUser=yes StateDirectory=kdrt \
               ProtectSystem=strict NoNewPrivileges=yes ProtectHome=yes PrivateTmp=yes \
               CapabilityBoundingSet= KillSignal=SIGTERM WantedBy=multi-user.target; do
    grep -qx "$setting" "$unit" || fail "$unit has no line $setting"
done
grep -q '^ExecStart=.* --cache-dir %S/kdrt$' "$unit" || fail "ExecStart does not keep the store in the state directory"
shutdown=$(sed -n 's/^ *"shutdown_timeout_s": *\([0-9]*\).*/\1/p' "$config")
stop=$(sed -n 's/^TimeoutStopSec=//p' "$unit")
[ -n "$shutdown" ] && [ -n "$stop" ] || fail "no shutdown_timeout_s in $config or TimeoutStopSec in $unit"
[ "$stop" -gt "$shutdown" ] || fail "TimeoutStopSec=$stop is not longer than shutdown_timeout_s=$shutdown"
echo "systemd_unit: ok ($unit; TimeoutStopSec=$stop, shutdown_timeout_s=$shutdown)"
