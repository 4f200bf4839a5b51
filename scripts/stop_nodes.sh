#!/bin/sh
# Stop the nodes started by scripts/start_nodes.sh (or `mds-ach start`): SIGTERM, clients and pipeline
# first, the daemon last; SIGKILL whatever is still running after a grace time. Only processes whose
# command line names the node are signalled, so a stale pid file never hits an unrelated program.
#
# Usage: scripts/stop_nodes.sh [GRACE_SECONDS]   (default 5)
# Environment: MDS_ACH_RUNTIME_DIR as for start_nodes.sh
set -eu

case "${1:-5}" in
    -h|--help) sed -n '2,8p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *[!0-9]*) echo "usage: $0 [GRACE_SECONDS]" >&2; exit 2 ;;
esac
grace=${1:-5}

if [ -n "${MDS_ACH_RUNTIME_DIR:-}" ]; then rt=$MDS_ACH_RUNTIME_DIR
elif [ -n "${XDG_RUNTIME_DIR:-}" ]; then rt=$XDG_RUNTIME_DIR/mds-ach
else rt=/tmp/mds-ach-$(id -u)
fi

node_pid() {  # node_pid NAME: the pid from NAME.pid if that process is alive and runs NAME
    [ -r "$rt/$1.pid" ] || return 1
    pid=$(cat "$rt/$1.pid")
    case "$pid" in ''|*[!0-9]*) return 1 ;; esac
    [ -r "/proc/$pid/cmdline" ] || return 1
    tr '\0' '\n' <"/proc/$pid/cmdline" | head -n 5 | grep -q "\(^\|/\)\(mds-ach-\)\{0,1\}$1\$" || return 1
    grep -q '^State:[[:space:]]*Z' "/proc/$pid/status" 2>/dev/null && return 1
    echo "$pid"
}

stop_group() {  # stop_group NAME...: SIGTERM them, wait up to $grace s, then SIGKILL
    pids=
    for name in "$@"; do
        if pid=$(node_pid "$name"); then
            kill -TERM "$pid" 2>/dev/null && pids="$pids $pid" && echo "  $name: SIGTERM (pid $pid)"
        fi
    done
    [ -n "$pids" ] || return 0
    steps=$((grace * 10))
    while [ "$steps" -gt 0 ]; do
        alive=
        for pid in $pids; do
            if kill -0 "$pid" 2>/dev/null && ! grep -q '^State:[[:space:]]*Z' "/proc/$pid/status" 2>/dev/null; then
                alive="$alive $pid"
            fi
        done
        [ -n "$alive" ] || return 0
        sleep 0.1
        steps=$((steps - 1))
    done
    for pid in $alive; do
        echo "  pid $pid still running after ${grace} s: SIGKILL"
        kill -KILL "$pid" 2>/dev/null || true
    done
}

stop_group bridge ik collision filter mux
stop_group daemon
for name in daemon mux filter collision ik bridge; do
    node_pid "$name" >/dev/null || rm -f "$rt/$name.pid"
done
echo "stopped"
